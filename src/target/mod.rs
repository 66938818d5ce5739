//! Rig descriptions (being built under issue 3).

/// Errors loading or validating a rig description.
#[derive(Debug, thiserror::Error)]
pub enum TargetError {
    #[error("cannot read rig file {path}")]
    Read {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

impl TargetError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            TargetError::Read { .. } => crate::exit::BAD_INPUT,
        }
    }
}
