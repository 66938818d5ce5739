//! Observation files (being built under issue 2).

#[derive(Debug, thiserror::Error)]
pub enum ObservationsError {
    #[error("cannot read {path}")]
    Read {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

impl ObservationsError {
    pub fn exit_code(&self) -> u8 {
        match self {
            ObservationsError::Read { .. } => crate::exit::BAD_INPUT,
        }
    }
}
