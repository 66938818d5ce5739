//! Protocol decoders and drivers fuzzed with proptest: random bytes, protocol-shaped strings and a
//! link that answers with random bytes. Nothing may panic, and a driver fed noise must fail with a
//! typed error within its exchange bound.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]

use std::io;
use std::time::{Duration, Instant};

use cubecal::turntable::grbl::{self, Axis, GrblConfig, GrblTurntable};
use cubecal::turntable::serial::Link;
use cubecal::turntable::zaber::{self, ZaberConfig, ZaberTurntable};
use cubecal::turntable::{Turntable, TurntableError};
use proptest::prelude::*;

/// A link that ignores what is sent and answers with scripted chunks, then silence.
struct Noise(Vec<Vec<u8>>);

impl Link for Noise {
    fn send(&mut self, _bytes: &[u8]) -> io::Result<()> {
        Ok(())
    }
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        if self.0.is_empty() {
            std::thread::sleep(timeout.min(Duration::from_millis(1)));
            return Ok(0);
        }
        let mut chunk = self.0.remove(0);
        let n = chunk.len().min(buf.len());
        buf[..n].copy_from_slice(&chunk[..n]);
        if n < chunk.len() {
            self.0.insert(0, chunk.split_off(n));
        }
        Ok(n)
    }
}

const EXCHANGE: Duration = Duration::from_millis(5);

fn grbl_driver(chunks: Vec<Vec<u8>>) -> GrblTurntable<Noise> {
    let config = GrblConfig {
        exchange_timeout: EXCHANGE,
        status_retries: 1,
        poll_interval: Duration::from_millis(1),
        move_timeout: Duration::from_millis(30),
        home_timeout: Duration::from_millis(30),
        startup_wait: Duration::from_millis(10),
        ..GrblConfig::new(Axis::X, 1.0)
    };
    GrblTurntable::new(Noise(chunks), config).unwrap()
}

fn zaber_driver(chunks: Vec<Vec<u8>>) -> ZaberTurntable<Noise> {
    let config = ZaberConfig {
        exchange_timeout: EXCHANGE,
        retries: 1,
        poll_interval: Duration::from_millis(1),
        move_timeout: Duration::from_millis(30),
        home_timeout: Duration::from_millis(30),
        ..ZaberConfig::new(1000.0)
    };
    ZaberTurntable::new(Noise(chunks), config).unwrap()
}

/// Protocol-shaped lines: fragments of real replies glued together at random.
fn grbl_like() -> impl Strategy<Value = String> {
    let piece = prop_oneof![
        Just("ok".to_string()),
        Just("error:".to_string()),
        Just("ALARM:".to_string()),
        Just("<".to_string()),
        Just(">".to_string()),
        Just("|".to_string()),
        Just("Idle".to_string()),
        Just("Run".to_string()),
        Just("Hold:".to_string()),
        Just("MPos:".to_string()),
        Just("WPos:".to_string()),
        Just("WCO:".to_string()),
        Just(",".to_string()),
        Just("[MSG:".to_string()),
        Just("Grbl ".to_string()),
        Just("$".to_string()),
        Just("=".to_string()),
        "-?[0-9]{0,12}(\\.[0-9]{0,6})?",
        "[ -~]{0,3}",
    ];
    prop::collection::vec(piece, 0..12).prop_map(|v| v.concat())
}

fn zaber_like() -> impl Strategy<Value = String> {
    let piece = prop_oneof![
        Just("@".to_string()),
        Just("!".to_string()),
        Just("#".to_string()),
        Just(" ".to_string()),
        Just("01".to_string()),
        Just("OK".to_string()),
        Just("RJ".to_string()),
        Just("IDLE".to_string()),
        Just("BUSY".to_string()),
        Just("--".to_string()),
        Just("FS".to_string()),
        Just("WR".to_string()),
        Just("BADDATA".to_string()),
        Just(":".to_string()),
        "-?[0-9]{0,20}",
        "[ -~]{0,3}",
    ];
    prop::collection::vec(piece, 0..12).prop_map(|v| v.concat())
}

fn assert_bounded(err: &TurntableError, elapsed: Duration, bound: Duration) {
    assert!(
        elapsed < bound,
        "took {elapsed:?} > {bound:?} to fail with {err}"
    );
}

proptest! {
    // Seeded so a run is reproducible; failures are also saved to a regressions file by proptest.
    #![proptest_config(ProptestConfig {
        cases: 256,
        rng_seed: proptest::test_runner::RngSeed::Fixed(0x0c0b_eca1),
        ..ProptestConfig::default()
    })]

    #[test]
    fn grbl_decoder_never_panics_on_bytes(bytes in prop::collection::vec(any::<u8>(), 0..200)) {
        let _ = grbl::decode_line(&bytes);
    }

    #[test]
    fn grbl_decoder_never_panics_on_protocol_shaped_text(s in grbl_like()) {
        if let Ok(grbl::Reply::Status(st)) = grbl::decode_line(s.as_bytes()) {
            // A decoded status always has a finite position list.
            let p = st.mpos.or(st.wpos).unwrap();
            prop_assert!(p.iter().all(|x| x.is_finite()));
        }
    }

    #[test]
    fn zaber_decoder_never_panics_on_bytes(bytes in prop::collection::vec(any::<u8>(), 0..200)) {
        let _ = zaber::decode_line(&bytes);
    }

    #[test]
    fn zaber_decoder_never_panics_on_protocol_shaped_text(s in zaber_like()) {
        if let Ok(zaber::Message::Reply(r)) = zaber::decode_line(s.as_bytes()) {
            prop_assert!(!r.data.is_empty());
        }
    }

    #[test]
    fn zaber_reply_round_trips(
        device in 1u8..=99, axis in 0u8..=9, busy: bool,
        flag in prop::sample::select(vec!["--", "FS", "WR", "NI", "QQ"]),
        data in -10_000_000i64..10_000_000,
    ) {
        let line = format!("@{device:02} {axis} OK {} {flag} {data}", if busy { "BUSY" } else { "IDLE" });
        match zaber::decode_line(line.as_bytes()) {
            Ok(zaber::Message::Reply(r)) => {
                prop_assert_eq!(r.device, device);
                prop_assert_eq!(r.axis, axis);
                prop_assert_eq!(r.data, data.to_string());
                prop_assert_eq!(r.warning.map(|f| f.code()).unwrap_or_else(|| "--".into()), flag);
            }
            other => prop_assert!(false, "{line} decoded as {other:?}"),
        }
    }

}

proptest! {
    // Each case waits out real (short) timeouts, so fewer cases.
    #![proptest_config(ProptestConfig {
        cases: 48,
        rng_seed: proptest::test_runner::RngSeed::Fixed(0x0c0b_eca2),
        ..ProptestConfig::default()
    })]

    #[test]
    fn grbl_driver_fed_noise_fails_typed_and_bounded(
        chunks in prop::collection::vec(prop::collection::vec(any::<u8>(), 0..64), 0..6),
    ) {
        let mut t = grbl_driver(chunks);
        let start = Instant::now();
        // position(): startup wait, then status query bound = exchange × (retries + 1);
        // move: move_timeout.
        if let Err(e) = t.position() {
            assert_bounded(&e, start.elapsed(), EXCHANGE * 4 + Duration::from_millis(50));
        }
        let start = Instant::now();
        if let Err(e) = t.move_to(cubecal::turntable::Degrees(10.0)) {
            assert_bounded(&e, start.elapsed(), Duration::from_millis(30 + 50));
        }
    }

    #[test]
    fn zaber_driver_fed_noise_fails_typed_and_bounded(
        chunks in prop::collection::vec(prop::collection::vec(any::<u8>(), 0..64), 0..6),
    ) {
        let mut t = zaber_driver(chunks);
        let start = Instant::now();
        if let Err(e) = t.position() {
            assert_bounded(&e, start.elapsed(), EXCHANGE * 2 + Duration::from_millis(50));
        }
        let start = Instant::now();
        if let Err(e) = t.move_to(cubecal::turntable::Degrees(10.0)) {
            assert_bounded(&e, start.elapsed(), Duration::from_millis(30 + 50));
        }
    }
}

/// A link that answers each send with the next scripted reply (possibly empty: silence).
struct Replies {
    script: std::collections::VecDeque<Vec<u8>>,
    pending: Vec<u8>,
}

impl Link for Replies {
    fn send(&mut self, _bytes: &[u8]) -> io::Result<()> {
        if let Some(r) = self.script.pop_front() {
            self.pending.extend(r);
        }
        Ok(())
    }
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        if self.pending.is_empty() {
            std::thread::sleep(timeout.min(Duration::from_millis(1)));
            return Ok(0);
        }
        let n = self.pending.len().min(buf.len());
        buf[..n].copy_from_slice(&self.pending[..n]);
        self.pending.drain(..n);
        Ok(n)
    }
}

fn grbl_scripted(script: &[&[u8]]) -> GrblTurntable<Replies> {
    let config = GrblConfig {
        exchange_timeout: Duration::from_millis(20),
        startup_wait: Duration::from_millis(200),
        ..GrblConfig::new(Axis::X, 1.0)
    };
    let link = Replies {
        script: script.iter().map(|r| r.to_vec()).collect(),
        pending: Vec::new(),
    };
    GrblTurntable::new(link, config).unwrap()
}

#[test]
fn grbl_banner_mid_operation_is_an_unexpected_restart() {
    let mut t = grbl_scripted(&[
        b"<Idle|MPos:0.000,0.000,0.000>\r\n", // wake-up ?
        b"\r\nGrbl 1.1h ['$' for help]\r\n",  // answer to the G0 line: it rebooted
    ]);
    let err = t.move_to(cubecal::turntable::Degrees(10.0)).unwrap_err();
    assert!(matches!(err, TurntableError::GrblRestarted), "{err:?}");
}

#[test]
fn grbl_boot_banner_on_connect_is_expected() {
    // What opening an Arduino looks like: the first ? is lost in the boot, the banner comes, then
    // answers.
    let mut t = grbl_scripted(&[
        b"",
        b"\r\nGrbl 1.1h ['$' for help]\r\n",
        b"<Idle|MPos:5.000,0.000,0.000>\r\n",
        b"<Idle|MPos:5.000,0.000,0.000>\r\n",
    ]);
    assert_eq!(t.position().unwrap(), cubecal::turntable::Degrees(5.0));
}

#[test]
fn grbl_late_status_reports_do_not_lag_the_position() {
    // The first ? is answered late (after its timeout), together with the retry's answer: the
    // newest report must win, and the next query must not read a leftover.
    let mut t = grbl_scripted(&[
        b"<Idle|MPos:0.000,0.000,0.000>\r\n", // wake-up
        b"",                                  // ? times out...
        b"<Run|MPos:1.000,0.000,0.000>\r\n<Idle|MPos:2.000,0.000,0.000>\r\n", // ...both arrive
        b"<Idle|MPos:3.000,0.000,0.000>\r\n",
    ]);
    assert_eq!(t.position().unwrap(), cubecal::turntable::Degrees(2.0));
    assert_eq!(t.position().unwrap(), cubecal::turntable::Degrees(3.0));
}
