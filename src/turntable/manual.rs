//! Turntables without a serial link: [`ManualTurntable`] (an operator turns the rig and confirms,
//! through an injectable [`Operator`]) and [`FixedRig`] (no turntable at all: one pose, 0°).

use std::io;

use super::{Degrees, Turntable, TurntableError};

/// Whoever turns a manual turntable. The CLI implements this on the terminal; tests script it.
pub trait Operator: Send {
    /// Show `instruction` and wait for the operator: `Ok(true)` when done, `Ok(false)` when declined.
    fn confirm(&mut self, instruction: &str) -> io::Result<bool>;
}

impl Operator for Box<dyn Operator> {
    fn confirm(&mut self, instruction: &str) -> io::Result<bool> {
        (**self).confirm(instruction)
    }
}

/// What the operator of a manual turntable is asked when the station homes it.
pub const HOME_INSTRUCTION: &str = "turn the turntable to its 0° mark";

/// A turntable turned by hand to marked angles. Positions are what the operator confirmed.
#[derive(Debug)]
pub struct ManualTurntable<O> {
    operator: O,
    position: Degrees,
    resolution: Degrees,
    /// The tilt limits of a cradle with marks, and its position.
    tilt: Option<((Degrees, Degrees), Degrees)>,
}

/// Default resolution of a hand-turned table with degree marks.
pub const MANUAL_RESOLUTION: Degrees = Degrees(1.0);

impl<O: Operator> ManualTurntable<O> {
    /// A manual table whose marks are `resolution` apart (e.g. [`MANUAL_RESOLUTION`]).
    pub fn new(operator: O, resolution: Degrees) -> Result<Self, TurntableError> {
        if !(resolution.0.is_finite() && resolution.0 > 0.0) {
            return Err(TurntableError::InvalidConfig {
                field: "resolution",
                reason: format!("must be finite and positive, got {}", resolution.0),
            });
        }
        Ok(ManualTurntable {
            operator,
            position: Degrees(0.0),
            resolution,
            tilt: None,
        })
    }

    /// The table stands on a cradle tilted by hand to marks within `limits`.
    pub fn with_tilt(mut self, limits: (Degrees, Degrees)) -> Self {
        self.tilt = Some((limits, Degrees(0.0)));
        self
    }

    fn mark(&self, a: Degrees) -> Degrees {
        Degrees((a.0 / self.resolution.0).round() * self.resolution.0)
    }

    /// Give the operator back.
    pub fn into_operator(self) -> O {
        self.operator
    }

    fn ask(&mut self, instruction: String) -> Result<(), TurntableError> {
        tracing::info!(%instruction, "asking the operator");
        match self.operator.confirm(&instruction) {
            Ok(true) => Ok(()),
            Ok(false) => Err(TurntableError::OperatorDeclined { instruction }),
            Err(source) => Err(TurntableError::Operator { source }),
        }
    }
}

impl<O: Operator> Turntable for ManualTurntable<O> {
    fn describe(&mut self) -> Result<String, TurntableError> {
        Ok(format!(
            "manual turntable (operator confirms each pose, marks every {})",
            self.resolution
        ))
    }

    fn home(&mut self) -> Result<Degrees, TurntableError> {
        self.ask(HOME_INSTRUCTION.into())?;
        self.position = Degrees(0.0);
        Ok(self.position)
    }

    fn move_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        let target = Degrees::checked(target.0)?;
        let mark = Degrees((target.0 / self.resolution.0).round() * self.resolution.0);
        self.ask(format!(
            "turn the turntable from {:.1} to {:.1}",
            self.position, mark
        ))?;
        self.position = mark;
        Ok(mark)
    }

    fn position(&mut self) -> Result<Degrees, TurntableError> {
        Ok(self.position)
    }

    fn stop(&mut self) -> Result<(), TurntableError> {
        Ok(())
    }

    fn resolution(&self) -> Degrees {
        self.resolution
    }

    fn tilt_limits(&self) -> Option<(Degrees, Degrees)> {
        self.tilt.map(|t| t.0)
    }

    fn tilt_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        let Some(((min, max), from)) = self.tilt else {
            return Err(TurntableError::NoTiltAxis { requested: target });
        };
        let mark = self.mark(Degrees::checked(target.0)?);
        super::check_tilt(mark, target, (min, max))?;
        self.ask(format!("tilt the cradle from {from:.1} to {mark:.1}"))?;
        self.tilt = Some(((min, max), mark));
        Ok(mark)
    }

    fn is_manual(&self) -> bool {
        true
    }

    /// One prompt for the whole pose: `instruction` as the station worded it.
    fn by_hand(
        &mut self,
        instruction: &str,
        rotation: Degrees,
        tilt: Option<Degrees>,
    ) -> Result<(Degrees, Option<Degrees>), TurntableError> {
        let rotation = self.mark(Degrees::checked(rotation.0)?);
        let tilt = match (tilt, self.tilt) {
            (Some(t), Some(((min, max), _))) => {
                let mark = self.mark(Degrees::checked(t.0)?);
                super::check_tilt(mark, t, (min, max))?;
                Some(mark)
            }
            (Some(t), None) => return Err(TurntableError::NoTiltAxis { requested: t }),
            (None, _) => None,
        };
        self.ask(instruction.to_string())?;
        self.position = rotation;
        if let (Some(t), Some((limits, _))) = (tilt, self.tilt) {
            self.tilt = Some((limits, t));
        }
        Ok((rotation, tilt))
    }
}

/// No turntable: the rig does not move. Homing succeeds, moves to 0° succeed, any other move is an error.
#[derive(Debug, Default, Clone, Copy)]
pub struct FixedRig;

impl Turntable for FixedRig {
    fn describe(&mut self) -> Result<String, TurntableError> {
        Ok("fixed rig (no turntable)".into())
    }

    fn home(&mut self) -> Result<Degrees, TurntableError> {
        Ok(Degrees(0.0))
    }

    fn move_to(&mut self, target: Degrees) -> Result<Degrees, TurntableError> {
        if target.0 == 0.0 {
            Ok(Degrees(0.0))
        } else {
            Err(TurntableError::FixedRig { requested: target })
        }
    }

    fn position(&mut self) -> Result<Degrees, TurntableError> {
        Ok(Degrees(0.0))
    }

    fn stop(&mut self) -> Result<(), TurntableError> {
        Ok(())
    }

    fn resolution(&self) -> Degrees {
        Degrees(0.0)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
mod tests {
    use super::*;

    struct Scripted(Vec<bool>, Vec<String>);
    impl Operator for Scripted {
        fn confirm(&mut self, instruction: &str) -> io::Result<bool> {
            self.1.push(instruction.to_string());
            Ok(self.0.pop().unwrap_or(false))
        }
    }

    #[test]
    fn confirmed_moves_land_on_marks_and_declines_are_errors() {
        let mut t =
            ManualTurntable::new(Scripted(vec![false, true, true], vec![]), MANUAL_RESOLUTION)
                .unwrap();
        assert_eq!(t.home().unwrap(), Degrees(0.0));
        assert_eq!(t.move_to(Degrees(30.2)).unwrap(), Degrees(30.0));
        assert!(matches!(
            t.move_to(Degrees(60.0)),
            Err(TurntableError::OperatorDeclined { .. })
        ));
        assert_eq!(t.position().unwrap(), Degrees(30.0));
        let asked = t.into_operator().1;
        assert_eq!(asked[1], "turn the turntable from 0.0° to 30.0°");
    }

    #[test]
    fn fixed_rig_refuses_to_move() {
        let mut r = FixedRig;
        assert!(r.move_to(Degrees(0.0)).is_ok());
        assert!(matches!(
            r.move_to(Degrees(30.0)),
            Err(TurntableError::FixedRig { .. })
        ));
    }
}
