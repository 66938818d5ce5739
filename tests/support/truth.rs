//! Calibrate from detected views and hold the intrinsics to the rendered camera (shared by the
//! render tests whose labels are decided only up to a motion that must not touch the intrinsics).

use cubecal::calib::{SolveOptions, View, solve};
use cubecal::camera::Camera;

/// Solve `views` and require an RMS below `max_rms_px` and fx, fy, cx, cy each within 5σ of the
/// solve's own uncertainty (plus 0.2 px for the renderer) of `camera`'s.
pub fn assert_calibrates_to(views: &[View], camera: &Camera, max_rms_px: f64) {
    let cal = solve(views, camera.image_size, &SolveOptions::default()).unwrap();
    let truth = [camera.fx(), camera.fy(), camera.cx(), camera.cy()];
    let got = [
        cal.camera.fx(),
        cal.camera.fy(),
        cal.camera.cx(),
        cal.camera.cy(),
    ];
    eprintln!(
        "truth {truth:.2?}, solved {got:.2?}, rms {:.3} px",
        cal.rms_px
    );
    assert!(cal.rms_px < max_rms_px, "rms {} px", cal.rms_px);
    for (k, (t, g)) in truth.iter().zip(got).enumerate() {
        let tol = 5.0 * cal.std_dev[k] + 0.2;
        assert!(
            (t - g).abs() < tol,
            "parameter {k}: {g} vs truth {t} (tol {tol})"
        );
    }
}
