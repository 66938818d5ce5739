//! The operator of a manual turntable (or of manual poses) on the terminal: a front-end concern, used
//! by `calibrate`; the station only sees the [`Operator`] trait.

use std::io::{BufRead, Write};

use cubecal::turntable::manual::Operator;

/// The operator of a manual turntable, on the terminal: instructions on stderr, Enter on stdin.
#[derive(Debug)]
pub(super) struct TerminalOperator;

impl Operator for TerminalOperator {
    #[allow(clippy::print_stderr)]
    fn confirm(&mut self, instruction: &str) -> std::io::Result<bool> {
        eprint!("Please {instruction}, then press Enter (or type n and Enter to abort): ");
        std::io::stderr().flush()?;
        let mut line = String::new();
        if std::io::stdin().lock().read_line(&mut line)? == 0 {
            return Err(std::io::Error::new(
                std::io::ErrorKind::UnexpectedEof,
                "stdin closed",
            ));
        }
        Ok(!matches!(line.trim(), "n" | "N" | "no"))
    }
}
