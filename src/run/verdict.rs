//! The station's verdict: a list of named checks, each with its measured value, the threshold it was
//! held against and whether it passed, plus a hint a person can act on when it did not.
//!
//! These names are an API (`--json` output, profiles, reports, the service's `STATUS=` line): keep them.

use serde::{Deserialize, Serialize};

/// One quality check of a calibration run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Check {
    /// Short stable identifier, e.g. `rms_px`, `coverage`, `sigma_fx_rel`, `held_out_rms_ratio`.
    pub name: String,
    /// The measured value.
    pub value: f64,
    /// The threshold the value was compared with (see `pass` for the direction).
    pub threshold: f64,
    /// Whether the check passed.
    pub pass: bool,
    /// What to do about a failing check (and, for a passing one, nothing).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hint: Option<String>,
}

impl Check {
    /// A check that passes when `value <= threshold` (NaN fails).
    pub fn at_most(name: &str, value: f64, threshold: f64, hint: impl FnOnce() -> String) -> Check {
        let pass = value <= threshold;
        Check {
            name: name.to_string(),
            value,
            threshold,
            pass,
            hint: (!pass).then(hint),
        }
    }

    /// A check that passes when `value >= threshold` (NaN fails).
    pub fn at_least(
        name: &str,
        value: f64,
        threshold: f64,
        hint: impl FnOnce() -> String,
    ) -> Check {
        let pass = value >= threshold;
        Check {
            name: name.to_string(),
            value,
            threshold,
            pass,
            hint: (!pass).then(hint),
        }
    }
}

/// A parameter the station held fixed instead of estimating it, at which value and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FixedParameter {
    /// The parameter (`k3`, `cx`, `p1`, `skew`, …).
    pub name: String,
    pub value: f64,
    /// Why: the configuration, or what the data left undetermined (with the estimate and σ).
    pub reason: String,
}

/// The verdict of a run: it passes when every check passes. `fixed` lists the parameters that
/// were not estimated, so that a pass says what it did not measure.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Verdict {
    pub pass: bool,
    pub checks: Vec<Check>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub fixed: Vec<FixedParameter>,
}

impl Verdict {
    pub fn from_checks(checks: Vec<Check>) -> Verdict {
        Verdict {
            pass: !checks.is_empty() && checks.iter().all(|c| c.pass),
            checks,
            fixed: Vec::new(),
        }
    }

    /// The failing checks, in order.
    pub fn failures(&self) -> impl Iterator<Item = &Check> {
        self.checks.iter().filter(|c| !c.pass)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn verdict_passes_only_when_every_check_does() {
        let ok = Check::at_most("rms_px", 0.1, 0.5, || "lower".into());
        let bad = Check::at_least("coverage", 0.34, 0.6, || "more".into());
        let nan = Check::at_most("nan", f64::NAN, 1.0, || "nan".into());
        assert!(ok.pass && ok.hint.is_none());
        assert!(!bad.pass && bad.hint.as_deref() == Some("more"));
        assert!(!nan.pass);
        assert!(Verdict::from_checks(vec![ok.clone()]).pass);
        assert!(!Verdict::from_checks(vec![ok, bad]).pass);
        assert!(!Verdict::from_checks(vec![]).pass);
    }
}
