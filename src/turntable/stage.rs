//! A two-axis stage: a rotation stage on a tilting cradle, each axis its own [`Turntable`] driver
//! (a GRBL controller's axis, a Zaber device), with limits per axis and homing of both.
//!
//! The tilt driver is a second driver on its own link rather than a second axis of one controller:
//! it keeps each driver's settle/timeout logic exactly as the one-axis contract tests it, and the same
//! code serves a second GRBL board, a second Zaber device on another port, or a simulator of either.

use super::{Degrees, Turntable, TurntableError};

/// Rotation plus tilt; see the module docs.
pub struct TiltStage {
    rotation: Box<dyn Turntable>,
    tilt: Box<dyn Turntable>,
    limits: (Degrees, Degrees),
}

impl std::fmt::Debug for TiltStage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TiltStage")
            .field("limits", &self.limits)
            .finish_non_exhaustive()
    }
}

impl TiltStage {
    /// `limits` are the tilt axis's (min, max); they must hold 0° (where homing leaves it).
    pub fn new(
        rotation: Box<dyn Turntable>,
        tilt: Box<dyn Turntable>,
        limits: (Degrees, Degrees),
    ) -> Result<TiltStage, TurntableError> {
        let (min, max) = limits;
        if !(min.0.is_finite()
            && max.0.is_finite()
            && min.0 <= 0.0
            && 0.0 <= max.0
            && min.0 < max.0)
        {
            return Err(TurntableError::InvalidConfig {
                field: "tilt limits",
                reason: format!("need min ≤ 0° ≤ max and min < max, got [{min}, {max}]"),
            });
        }
        Ok(TiltStage {
            rotation,
            tilt,
            limits,
        })
    }
}

impl Turntable for TiltStage {
    fn describe(&mut self) -> Result<String, TurntableError> {
        Ok(format!(
            "rotation: {}; tilt [{}, {}]: {}",
            self.rotation.describe()?,
            self.limits.0,
            self.limits.1,
            self.tilt.describe()?
        ))
    }

    /// Homes the tilt first (level cradle), then the rotation; returns the rotation's position.
    fn home(&mut self) -> Result<Degrees, TurntableError> {
        self.tilt.home()?;
        self.rotation.home()
    }

    fn move_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        self.rotation.move_to(target)
    }

    fn position(&mut self) -> Result<Degrees, TurntableError> {
        self.rotation.position()
    }

    /// Stops both axes (the first error is reported after both were asked).
    fn stop(&mut self) -> Result<(), TurntableError> {
        let a = self.rotation.stop();
        let b = self.tilt.stop();
        a.and(b)
    }

    fn resolution(&self) -> Degrees {
        self.rotation.resolution()
    }

    fn tilt_limits(&self) -> Option<(Degrees, Degrees)> {
        Some(self.limits)
    }

    fn tilt_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        super::check_tilt(target, target, self.limits)?;
        self.tilt.move_to(target)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
mod tests {
    use super::*;
    use crate::turntable::fake::FakeTurntable;

    #[test]
    fn tilt_stage_moves_each_axis_and_keeps_the_limits() {
        let mut s = TiltStage::new(
            Box::new(FakeTurntable::new()),
            Box::new(FakeTurntable::new()),
            (Degrees(-30.0), Degrees(30.0)),
        )
        .unwrap();
        s.home().unwrap();
        assert_eq!(s.move_to(Degrees(40.0)).unwrap(), Degrees(40.0));
        assert_eq!(s.tilt_to(Degrees(-20.0)).unwrap(), Degrees(-20.0));
        assert_eq!(s.position().unwrap(), Degrees(40.0));
        assert!(matches!(
            s.tilt_to(Degrees(31.0)),
            Err(TurntableError::BeyondLimit { .. })
        ));
        assert!(
            TiltStage::new(
                Box::new(FakeTurntable::new()),
                Box::new(FakeTurntable::new()),
                (Degrees(5.0), Degrees(30.0)),
            )
            .is_err()
        );
    }
}
