//! Byte links, line framing with deadlines, and opening a serial port with its errors sorted into kinds.

use std::io;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use super::{TurntableError, escape_bytes};

/// Longest line accepted before the bytes are handed up as one (garbage) line; both protocols' lines
/// are well under 128 bytes.
pub const MAX_LINE_BYTES: usize = 256;

/// A byte stream to a stage: the only thing a driver needs from a serial port.
pub trait Link: Send {
    /// Write all of `bytes`.
    fn send(&mut self, bytes: &[u8]) -> io::Result<()>;
    /// Wait at most `timeout` for some bytes. `Ok(0)` means none arrived in time; a closed port is an
    /// error (`UnexpectedEof` or `BrokenPipe`), never `Ok(0)`.
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize>;
}

/// Time the serial layer may spend on one write (a stalled USB adapter must not hang us).
const WRITE_TIMEOUT: Duration = Duration::from_millis(500);

fn port_send<P: SerialPort + ?Sized>(port: &mut P, bytes: &[u8]) -> io::Result<()> {
    port.set_timeout(WRITE_TIMEOUT)?;
    // No flush(): it is tcdrain(), which can wait on the other end; write() already hands the bytes to
    // the kernel.
    port.write_all(bytes)
}

fn port_receive<P: SerialPort + ?Sized>(
    port: &mut P,
    buf: &mut [u8],
    timeout: Duration,
) -> io::Result<usize> {
    port.set_timeout(timeout)?;
    match port.read(buf) {
        Ok(0) => Err(io::Error::new(
            io::ErrorKind::UnexpectedEof,
            "end of file on serial port",
        )),
        Ok(n) => Ok(n),
        Err(e)
            if matches!(
                e.kind(),
                io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock
            ) =>
        {
            Ok(0)
        }
        Err(e) => Err(e),
    }
}

impl<P: SerialPort + ?Sized> Link for Box<P> {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        port_send(&mut **self, bytes)
    }
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        port_receive(&mut **self, buf, timeout)
    }
}

impl Link for TTYPort {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        port_send(self, bytes)
    }
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        port_receive(self, buf, timeout)
    }
}

/// Is this I/O error the port going away (as opposed to a transient failure)?
pub fn is_disconnect(e: &io::Error) -> bool {
    // A pty whose other end closed reports POLLHUP (BrokenPipe) or EIO (Other, raw os error 5); an
    // unplugged USB adapter reports EIO or ENXIO/ENODEV.
    matches!(
        e.kind(),
        io::ErrorKind::BrokenPipe
            | io::ErrorKind::UnexpectedEof
            | io::ErrorKind::NotConnected
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::NotFound
    ) || matches!(e.raw_os_error(), Some(5 | 6 | 19))
        // serialport turns EIO into an `Other` error carrying only nix's description.
        || (e.kind() == io::ErrorKind::Other && e.to_string() == "I/O error")
}

/// Turn an I/O error into the right [`TurntableError`].
pub fn io_error(during: impl Into<String>, e: io::Error) -> TurntableError {
    let during = during.into();
    if is_disconnect(&e) {
        TurntableError::Disconnected { during, source: e }
    } else {
        TurntableError::Io { during, source: e }
    }
}

/// Why [`LineIo::read_line`] returned without a line.
#[derive(Debug)]
pub enum LineError {
    /// The deadline passed; `partial` holds the bytes received without a line ending.
    TimedOut { partial: Vec<u8> },
    /// The link failed.
    Io(io::Error),
}

/// A [`Link`] with a receive buffer that splits the stream into lines (`\n`-terminated, `\r` stripped).
#[derive(Debug)]
pub struct LineIo<L> {
    link: L,
    pending: Vec<u8>,
}

impl<L: Link> LineIo<L> {
    /// Wrap a link.
    pub fn new(link: L) -> Self {
        LineIo {
            link,
            pending: Vec::new(),
        }
    }

    /// Give the link back.
    pub fn into_inner(self) -> L {
        self.link
    }

    /// Write bytes.
    pub fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.link.send(bytes)
    }

    /// Drop buffered bytes and whatever arrives within `quiet` (stale replies before a re-send).
    pub fn drain(&mut self, quiet: Duration) -> io::Result<()> {
        self.pending.clear();
        let mut buf = [0u8; 256];
        let until = Instant::now() + quiet;
        loop {
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(());
            }
            if self.link.receive(&mut buf, left)? == 0 {
                return Ok(());
            }
        }
    }

    /// Forget a partial line (the tail of garbage) received so far.
    pub fn drop_partial(&mut self) {
        self.pending.clear();
    }

    /// The next complete line already received, without waiting; a partial line stays buffered.
    pub fn try_line(&mut self) -> io::Result<Option<Vec<u8>>> {
        if let Some(line) = self.take_line() {
            return Ok(Some(line));
        }
        let mut buf = [0u8; 256];
        let n = self.link.receive(&mut buf, Duration::ZERO)?;
        self.pending.extend_from_slice(&buf[..n]);
        Ok(self.take_line())
    }

    /// Read the next non-empty line before `deadline`. Lines longer than [`MAX_LINE_BYTES`] are cut
    /// and returned as they are (the caller will find them unexpected).
    pub fn read_line(&mut self, deadline: Instant) -> Result<Vec<u8>, LineError> {
        let mut buf = [0u8; 256];
        loop {
            if let Some(line) = self.take_line() {
                return Ok(line);
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(LineError::TimedOut {
                    partial: std::mem::take(&mut self.pending),
                });
            }
            match self.link.receive(&mut buf, left) {
                Ok(n) => self.pending.extend_from_slice(&buf[..n]),
                Err(e) => return Err(LineError::Io(e)),
            }
        }
    }

    fn take_line(&mut self) -> Option<Vec<u8>> {
        loop {
            let end = match self.pending.iter().position(|&b| b == b'\n') {
                Some(i) => i,
                None if self.pending.len() > MAX_LINE_BYTES => MAX_LINE_BYTES,
                None => return None,
            };
            let mut line: Vec<u8> = self.pending.drain(..end).collect();
            if self.pending.first() == Some(&b'\n') {
                self.pending.remove(0);
            }
            line.retain(|&b| b != b'\r');
            if !line.is_empty() {
                return Some(line);
            }
        }
    }
}

/// Open a serial port at `baud` (8N1), sorting failures into not-found / busy / permission / other.
pub fn open_port(path: &str, baud: u32) -> Result<Box<dyn SerialPort>, TurntableError> {
    tracing::debug!(path, baud, "opening turntable port");
    serialport::new(path, baud)
        .timeout(Duration::from_millis(100))
        .open()
        .map_err(|source| classify_open_error(path, source))
}

/// Sort a `serialport` open error into a typed [`TurntableError`].
pub fn classify_open_error(path: &str, source: serialport::Error) -> TurntableError {
    let path = path.to_string();
    match source.kind() {
        // serialport reports EBUSY (TIOCEXCL held by someone else) as NoDevice.
        serialport::ErrorKind::NoDevice => TurntableError::PortBusy { path, source },
        serialport::ErrorKind::Io(io::ErrorKind::NotFound) => {
            TurntableError::PortNotFound { path, source }
        }
        serialport::ErrorKind::Io(io::ErrorKind::PermissionDenied) => {
            TurntableError::PermissionDenied { path, source }
        }
        _ => TurntableError::Open { path, source },
    }
}

/// Describe a line-read failure as a [`TurntableError`] for `command`.
pub fn line_error(command: &str, e: LineError, timeout: Duration, attempts: u32) -> TurntableError {
    match e {
        LineError::TimedOut { partial } => TurntableError::Timeout {
            command: command.to_string(),
            timeout,
            attempts,
            received: escape_bytes(&partial),
        },
        LineError::Io(e) => io_error(format!("waiting for the reply to {command}"), e),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
mod tests {
    use super::*;

    /// A link that hands out scripted chunks, one per receive call.
    struct Script(Vec<Vec<u8>>);
    impl Link for Script {
        fn send(&mut self, _bytes: &[u8]) -> io::Result<()> {
            Ok(())
        }
        fn receive(&mut self, buf: &mut [u8], _timeout: Duration) -> io::Result<usize> {
            if self.0.is_empty() {
                std::thread::sleep(Duration::from_millis(1));
                return Ok(0);
            }
            let chunk = self.0.remove(0);
            buf[..chunk.len()].copy_from_slice(&chunk);
            Ok(chunk.len())
        }
    }

    #[test]
    fn lines_are_reassembled_across_chunks_and_cr_stripped() {
        let mut io = LineIo::new(Script(vec![
            b"\r\nGrbl 1.1h".to_vec(),
            b" ['$' for help]\r\nok\r".to_vec(),
            b"\n<Idle|MPos:0.000,0.000,0.000>\r\npartial".to_vec(),
        ]));
        let deadline = Instant::now() + Duration::from_millis(50);
        assert_eq!(
            io.read_line(deadline).unwrap(),
            b"Grbl 1.1h ['$' for help]".to_vec()
        );
        assert_eq!(io.read_line(deadline).unwrap(), b"ok".to_vec());
        assert_eq!(
            io.read_line(deadline).unwrap(),
            b"<Idle|MPos:0.000,0.000,0.000>".to_vec()
        );
        match io.read_line(deadline) {
            Err(LineError::TimedOut { partial }) => assert_eq!(partial, b"partial".to_vec()),
            other => panic!("expected a timeout, got {other:?}"),
        }
    }

    #[test]
    fn open_errors_are_sorted_into_kinds() {
        use serialport::{Error, ErrorKind};
        let cases = [
            (ErrorKind::NoDevice, "busy"),
            (ErrorKind::Io(io::ErrorKind::NotFound), "does not exist"),
            (
                ErrorKind::Io(io::ErrorKind::PermissionDenied),
                "permission denied",
            ),
            (ErrorKind::Unknown, "cannot open"),
        ];
        for (kind, says) in cases {
            let e = classify_open_error("/dev/ttyUSB0", Error::new(kind, "x"));
            assert!(e.to_string().contains(says), "{e}");
            assert_eq!(e.exit_code(), crate::exit::DEVICE);
        }
        assert!(matches!(
            classify_open_error(
                "p",
                Error::new(ErrorKind::Io(io::ErrorKind::PermissionDenied), "x")
            ),
            TurntableError::PermissionDenied { .. }
        ));
    }

    #[test]
    fn overlong_garbage_is_returned_as_a_line() {
        let mut io = LineIo::new(Script(vec![vec![b'x'; 200]; 3]));
        let deadline = Instant::now() + Duration::from_millis(50);
        assert_eq!(io.read_line(deadline).unwrap().len(), MAX_LINE_BYTES);
    }
}
