//! Turntable: the `Turntable` trait, GRBL and Zaber ASCII serial drivers, a manual driver and simulators.
//! (Being built under issue 6.)

/// Errors from turntable drivers.
#[derive(Debug, thiserror::Error)]
pub enum TurntableError {
    /// The serial port could not be opened.
    #[error("cannot open turntable port {path}")]
    Open {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

impl TurntableError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            TurntableError::Open { .. } => crate::exit::DEVICE,
        }
    }
}
