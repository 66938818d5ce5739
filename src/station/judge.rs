//! The verdict: every check a calibration engineer would make before trusting a result, each with
//! its value, threshold and a hint a person can act on.
//!
//! | check | passes when |
//! |---|---|
//! | `views` | views in the fit ≥ `qa.min_views` |
//! | `converged` | the solver converged (1) |
//! | `rms_px` | residual RMS ≤ `qa.max_rms_px` |
//! | `max_residual_px` | largest residual ≤ `qa.max_residual_px` |
//! | `coverage` | covered fraction of the coverage grid ≥ `qa.min_coverage` |
//! | `sigma_fx_rel`, `sigma_fy_rel` | σ(f)/f ≤ `qa.max_sigma_fx_rel` |
//! | `sigma_cx_px`, `sigma_cy_px` | σ ≤ `qa.max_sigma_cx_px` |
//! | `held_out_rms_px:<view>` | held-out RMS ≤ `qa.max_held_out_ratio` × fit RMS + `qa.held_out_floor_px` |

use nalgebra::Vector2;

use super::config::StationConfig;
use super::coverage::Coverage;
use super::{HeldOut, ViewRecord};
use crate::calib::{CalibError, Calibration, View};
use crate::camera::idx;
use crate::run::{Check, Verdict};

/// What the verdict is made from.
#[derive(Debug)]
pub struct Inputs<'a> {
    pub cfg: &'a StationConfig,
    pub cal: &'a Calibration,
    pub fit_views: usize,
    pub coverage: &'a Coverage,
    pub max_residual_px: f64,
    pub held_out: &'a [HeldOut],
    pub held_failures: &'a [(String, CalibError)],
    pub views: &'a [ViewRecord],
}

/// The largest residual norm over the fit's inlier points (px).
pub fn max_residual(cal: &Calibration, views: &[View]) -> f64 {
    let mut max = 0.0_f64;
    for (v, r) in views.iter().zip(&cal.views) {
        for (i, p) in v.points.iter().enumerate() {
            if r.outliers.contains(&i) {
                continue;
            }
            if let Ok(uv) = cal.camera.project(&r.cam_from_rig, &p.xyz) {
                let d: Vector2<f64> = p.uv - uv;
                max = max.max(d.norm());
            }
        }
    }
    max
}

fn rejected_summary(views: &[ViewRecord]) -> String {
    let rejected: Vec<&ViewRecord> = views.iter().filter(|v| !v.accepted).collect();
    if rejected.is_empty() {
        return String::new();
    }
    let first = rejected
        .iter()
        .find_map(|v| v.reason.as_deref())
        .unwrap_or("no reason");
    format!(
        "; {} of {} pose(s) were rejected (e.g. {}: {first})",
        rejected.len(),
        views.len(),
        rejected[0].name
    )
}

fn views_check(n: usize, cfg: &StationConfig, views: &[ViewRecord]) -> Check {
    Check::at_least("views", n as f64, cfg.qa.min_views as f64, || {
        format!(
            "only {n} usable view(s) in the fit, at least {} needed{}",
            cfg.qa.min_views,
            rejected_summary(views)
        )
    })
}

/// The verdict when fewer than two views could be used (no calibration at all).
pub fn too_few_views(n: usize, cfg: &StationConfig, views: &[ViewRecord]) -> Verdict {
    Verdict::from_checks(vec![views_check(n, cfg, views)])
}

/// The verdict when the solver failed.
pub fn solve_failed(e: &CalibError, n: usize, cfg: &StationConfig) -> Verdict {
    Verdict::from_checks(vec![
        Check::at_least("views", n as f64, cfg.qa.min_views as f64, || {
            "too few views".into()
        }),
        Check {
            name: "converged".into(),
            value: 0.0,
            threshold: 1.0,
            pass: false,
            hint: Some(format!("the solver failed: {e}")),
        },
    ])
}

/// Judge a calibration.
pub fn judge(inp: &Inputs<'_>) -> Verdict {
    let q = &inp.cfg.qa;
    let cal = inp.cal;
    let mut checks = vec![views_check(inp.fit_views, inp.cfg, inp.views)];
    let converged = cal.termination.is_converged();
    checks.push(Check {
        name: "converged".into(),
        value: if converged { 1.0 } else { 0.0 },
        threshold: 1.0,
        pass: converged,
        hint: (!converged).then(|| {
            format!(
                "the solver stopped without converging ({})",
                cal.termination.as_str()
            )
        }),
    });
    checks.push(Check::at_most("rms_px", cal.rms_px, q.max_rms_px, || {
        format!(
            "residual RMS {:.3} px exceeds {:.3} px: blur, a rig file that does not match the printed rig, or a camera that changed during the run",
            cal.rms_px, q.max_rms_px
        )
    }));
    checks.push(Check::at_most(
        "max_residual_px",
        inp.max_residual_px,
        q.max_residual_px,
        || {
            format!(
                "a corner reprojects {:.2} px off (at most {:.2}): a mis-detected corner or a warped board",
                inp.max_residual_px, q.max_residual_px
            )
        },
    ));
    let cov = inp.coverage;
    checks.push(Check::at_least("coverage", cov.fraction(), q.min_coverage, || {
        let empty = cov.empty_regions();
        format!(
            "corners cover {:.0} % of the image (at least {:.0} % needed); add poses that put the rig near the image corners{}",
            100.0 * cov.fraction(),
            100.0 * q.min_coverage,
            if empty.is_empty() {
                String::new()
            } else {
                format!(" (empty: {})", empty.join(", "))
            }
        )
    }));
    let sd = &cal.std_dev;
    let more = "add views (more poses, tilts, the rig nearer the image corners)";
    if cal.estimated[idx::FX] {
        let v = sd[idx::FX] / cal.camera.fx();
        checks.push(Check::at_most(
            "sigma_fx_rel",
            v,
            q.max_sigma_fx_rel,
            || format!("fx is uncertain to {:.3} %; {more}", 100.0 * v),
        ));
    }
    if cal.estimated[idx::FY] {
        let v = sd[idx::FY] / cal.camera.fy();
        checks.push(Check::at_most(
            "sigma_fy_rel",
            v,
            q.max_sigma_fx_rel,
            || format!("fy is uncertain to {:.3} %; {more}", 100.0 * v),
        ));
    }
    if cal.estimated[idx::CX] {
        checks.push(Check::at_most(
            "sigma_cx_px",
            sd[idx::CX],
            q.max_sigma_cx_px,
            || format!("cx is uncertain to {:.2} px; {more}", sd[idx::CX]),
        ));
    }
    if cal.estimated[idx::CY] {
        checks.push(Check::at_most(
            "sigma_cy_px",
            sd[idx::CY],
            q.max_sigma_cx_px,
            || format!("cy is uncertain to {:.2} px; {more}", sd[idx::CY]),
        ));
    }
    let limit = q.max_held_out_ratio * cal.rms_px + q.held_out_floor_px;
    for h in inp.held_out {
        checks.push(Check::at_most(
            &format!("held_out_rms_px:{}", h.name),
            h.rms_px,
            limit,
            || {
                format!(
                    "the held-out pose '{}' reprojects with RMS {:.3} px through this calibration, against {:.3} px in the fit: the camera changed during the run (focus, zoom, a knock) or that pose is bad; lock the focus and re-run",
                    h.name, h.rms_px, cal.rms_px
                )
            },
        ));
    }
    for (name, e) in inp.held_failures {
        checks.push(Check {
            name: format!("held_out_rms_px:{name}"),
            value: f64::NAN,
            threshold: limit,
            pass: false,
            hint: Some(format!(
                "the held-out pose '{name}' could not be placed with this calibration: {e}"
            )),
        });
    }
    Verdict::from_checks(checks)
}
