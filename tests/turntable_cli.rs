//! `cubecal turntable ...` end to end: a simulator subprocess on a pty, the bring-up commands against
//! it, and the port-problem messages and exit codes.

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Output, Stdio};

const BIN: &str = env!("CARGO_BIN_EXE_cubecal");

/// A `cubecal turntable simulate` child process, killed on drop.
struct Simulator {
    child: Child,
    port: String,
}

impl Simulator {
    fn start(protocol: &str, extra: &[&str]) -> Simulator {
        let mut child = Command::new(BIN)
            .args(["--json", "turntable", "simulate", "--protocol", protocol])
            .args([
                "--seconds",
                "20",
                "--speed-deg-s",
                "3600",
                "--accel-deg-s2",
                "36000",
            ])
            .args(extra)
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        let v: serde_json::Value = serde_json::from_str(&line).unwrap();
        assert_eq!(v["protocol"], protocol);
        let port = v["port"].as_str().unwrap().to_string();
        Simulator { child, port }
    }
}

impl Drop for Simulator {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn cubecal(args: &[&str]) -> Output {
    Command::new(BIN).args(args).output().unwrap()
}

fn json(out: &Output) -> serde_json::Value {
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "stdout is not JSON ({e}): {}\nstderr: {}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )
    })
}

#[test]
fn grbl_bring_up_against_the_simulator() {
    let sim = Simulator::start("grbl", &["--homing", "--axis", "A"]);
    let conn = [
        "--protocol",
        "grbl",
        "--port",
        &sim.port,
        "--axis",
        "A",
        "--homing",
    ];
    let probe = cubecal(&[&["--json", "turntable", "probe"][..], &conn].concat());
    assert!(probe.status.success(), "{probe:?}");
    assert!(
        json(&probe)["device"]
            .as_str()
            .unwrap()
            .starts_with("GRBL 1.1h")
    );

    let home = cubecal(&[&["--json", "turntable", "home"][..], &conn].concat());
    assert!(home.status.success(), "{home:?}");

    let mv = cubecal(&[&["--json", "turntable", "move", "-30"][..], &conn].concat());
    assert!(mv.status.success(), "{mv:?}");
    assert_eq!(json(&mv)["position_deg"], -30.0);

    let status = cubecal(&[&["turntable", "status"][..], &conn].concat());
    assert!(status.status.success(), "{status:?}");
    assert_eq!(
        String::from_utf8_lossy(&status.stdout).trim(),
        "position -30.0°"
    );
}

#[test]
fn zaber_bring_up_against_the_simulator() {
    let sim = Simulator::start("zaber", &[]);
    let conn = ["--protocol", "zaber", "--port", &sim.port];
    let home = cubecal(&[&["turntable", "home"][..], &conn].concat());
    assert!(home.status.success(), "{home:?}");
    let mv = cubecal(&[&["--json", "turntable", "move", "330"][..], &conn].concat());
    assert!(mv.status.success(), "{mv:?}");
    let v = json(&mv);
    assert!((v["position_deg"].as_f64().unwrap() - 330.0).abs() <= 0.000_234_375);
}

#[test]
fn alarm_fault_exits_with_the_device_code_and_the_meaning() {
    let sim = Simulator::start("grbl", &["--fault", "alarm"]);
    let out = cubecal(&[
        "turntable",
        "move",
        "90",
        "--protocol",
        "grbl",
        "--port",
        &sim.port,
    ]);
    assert_eq!(out.status.code(), Some(4), "{out:?}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("GRBL alarm 1: Hard limit triggered"),
        "{stderr}"
    );
}

#[test]
fn missing_port_says_so_and_exits_4() {
    let out = cubecal(&[
        "--json",
        "turntable",
        "status",
        "--protocol",
        "grbl",
        "--port",
        "/dev/ttyCUBECAL-none",
    ]);
    assert_eq!(out.status.code(), Some(4));
    let v = json(&out);
    assert_eq!(v["exit_code"], 4);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("does not exist"), "{stderr}");
    assert!(stderr.contains("check the cable"), "{stderr}");
}

#[test]
fn busy_port_says_so_and_exits_4() {
    let sim = Simulator::start("grbl", &[]);
    // Hold the port exclusively (TIOCEXCL + flock), as another program would.
    let _holder = serialport::new(&sim.port, 115_200).open().unwrap();
    let out = cubecal(&[
        "turntable",
        "status",
        "--protocol",
        "grbl",
        "--port",
        &sim.port,
    ]);
    assert_eq!(out.status.code(), Some(4), "{out:?}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("is busy"), "{stderr}");
}

#[test]
fn serial_protocols_need_a_port() {
    // A usage error (issue 17, item 7), found by the argument parser before anything is opened.
    let out = cubecal(&["turntable", "move", "30", "--protocol", "zaber"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--port"));
}

#[test]
fn fixed_rig_refuses_to_move_with_bad_input() {
    let out = cubecal(&["turntable", "move", "-30", "--protocol", "none"]);
    assert_eq!(out.status.code(), Some(3), "{out:?}");
    let ok = cubecal(&["turntable", "move", "0", "--protocol", "none"]);
    assert!(ok.status.success());
}
