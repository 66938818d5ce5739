//! An in-memory [`Turntable`]: instant moves, a record of every call, and scripted failures.
//! For tests of code that drives a turntable (the station) and as the reference in the contract suite.

use std::collections::VecDeque;

use super::{Degrees, Turntable, TurntableError};

/// One call made on a [`FakeTurntable`].
#[derive(Debug, Clone, PartialEq)]
pub enum FakeCall {
    Describe,
    Home,
    MoveTo(Degrees),
    Position,
    Stop,
}

/// An instant turntable that quantises positions to its resolution, like a stepper stage.
#[derive(Debug)]
pub struct FakeTurntable {
    position: Degrees,
    homed: bool,
    resolution: Degrees,
    calls: Vec<FakeCall>,
    failures: VecDeque<TurntableError>,
}

/// Resolution of [`FakeTurntable::new`]: 0.001°.
pub const FAKE_RESOLUTION: Degrees = Degrees(0.001);

impl Default for FakeTurntable {
    fn default() -> Self {
        FakeTurntable::new()
    }
}

impl FakeTurntable {
    /// An un-homed fake at an arbitrary start angle (17°), resolution [`FAKE_RESOLUTION`].
    pub fn new() -> Self {
        FakeTurntable {
            position: Degrees(17.0),
            homed: false,
            resolution: FAKE_RESOLUTION,
            calls: Vec::new(),
            failures: VecDeque::new(),
        }
    }

    /// Make the next operation (any trait method but `resolution`) fail with `error`. Failures queue.
    pub fn fail_next(&mut self, error: TurntableError) {
        self.failures.push_back(error);
    }

    /// Every call so far, in order.
    pub fn calls(&self) -> &[FakeCall] {
        &self.calls
    }

    /// Whether `home` has succeeded.
    pub fn is_homed(&self) -> bool {
        self.homed
    }

    fn record(&mut self, call: FakeCall) -> Result<(), TurntableError> {
        self.calls.push(call);
        match self.failures.pop_front() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    fn quantise(&self, a: Degrees) -> Degrees {
        Degrees((a.0 / self.resolution.0).round() * self.resolution.0)
    }
}

impl Turntable for FakeTurntable {
    fn describe(&mut self) -> Result<String, TurntableError> {
        self.record(FakeCall::Describe)?;
        Ok("in-memory fake turntable".into())
    }

    fn home(&mut self) -> Result<Degrees, TurntableError> {
        self.record(FakeCall::Home)?;
        self.position = Degrees(0.0);
        self.homed = true;
        Ok(self.position)
    }

    fn move_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        self.record(FakeCall::MoveTo(target))?;
        let target = Degrees::checked(target.0)?;
        self.position = self.quantise(target);
        Ok(self.position)
    }

    fn position(&mut self) -> Result<Degrees, TurntableError> {
        self.record(FakeCall::Position)?;
        Ok(self.position)
    }

    fn stop(&mut self) -> Result<(), TurntableError> {
        self.record(FakeCall::Stop)
    }

    fn resolution(&self) -> Degrees {
        self.resolution
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
mod tests {
    use super::*;

    #[test]
    fn scripted_failure_is_returned_once_and_recorded() {
        let mut t = FakeTurntable::new();
        t.fail_next(TurntableError::GrblLocked);
        assert!(matches!(t.home(), Err(TurntableError::GrblLocked)));
        assert!(t.home().is_ok());
        assert_eq!(t.calls(), &[FakeCall::Home, FakeCall::Home]);
    }
}
