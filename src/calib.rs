//! Solvers (being built under issue 2).

/// Errors from the solvers.
#[derive(Debug, thiserror::Error)]
pub enum CalibError {
    #[error("too few points: {got} given, {need} needed")]
    TooFewPoints { got: usize, need: usize },
}

impl CalibError {
    pub fn exit_code(&self) -> u8 {
        match self {
            CalibError::TooFewPoints { .. } => crate::exit::BAD_INPUT,
        }
    }
}
