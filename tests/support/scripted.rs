//! An operator for manual-turntable tests: does what each prompt says (confirms) and remembers the
//! prompts, for the test to read through its clone.
#![allow(dead_code, clippy::unwrap_used)]

use std::sync::{Arc, Mutex};

use cubecal::turntable::manual::Operator;

#[derive(Debug, Clone, Default)]
pub struct Scripted(pub Arc<Mutex<Vec<String>>>);

impl Operator for Scripted {
    fn confirm(&mut self, instruction: &str) -> std::io::Result<bool> {
        self.0.lock().unwrap().push(instruction.to_string());
        Ok(true)
    }
}
