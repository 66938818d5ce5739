//! A profile document as a station writes it, for the PostgreSQL store's tests and benchmark.

use cubecal::profile::{Profile, parse_document};

/// Version `n` of a camera's profile (fx = 1000 + n/1000, σ 0.5), from a document as a station writes
/// it; `pass` false gives a failing verdict.
pub fn profile(identity: &str, n: u64, pass: bool) -> Profile {
    let fx = 1000.0 + n as f64 / 1000.0;
    let names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"];
    let doc = serde_json::json!({
        "format_version": 1,
        "identity": { "id": identity, "origin": "user" },
        "calibration": {
            "image_size": [1280, 960],
            "camera_matrix": [[fx, 0.0, 639.5], [0.0, fx * 1.001, 479.5], [0.0, 0.0, 1.0]],
            "distortion": { "model": "brown5", "coefficients": [-0.3, 0.1, 0.001, -0.0008, -0.01] },
            "std_dev": names.iter().map(|n| (n.to_string(), serde_json::json!(0.5))).collect::<serde_json::Map<_, _>>(),
            "free_params": names,
            "covariance": (0..9).map(|i| (0..9).map(|j| if i == j { 0.25 } else { 0.0 }).collect::<Vec<f64>>()).collect::<Vec<_>>(),
            "rms_px": 0.1, "rms_reprojection_px": 0.14, "sigma_px": 0.1,
            "n_points": 1000, "n_params": 69, "views": [], "iterations": 7,
            "termination": "converged", "converged": true, "init_method": "dlt"
        },
        "verdict": { "pass": pass, "checks": [
            { "name": "rms_px", "value": if pass { 0.1 } else { 0.9 }, "threshold": 0.5, "pass": pass }
        ] },
        "rig": { "name": "cube_outside", "sha256": "0".repeat(64) },
        "software_version": env!("CARGO_PKG_VERSION"),
        "created": cubecal::profile::rfc3339_from_unix(1_790_000_000 + n),
    });
    let bytes = serde_json::to_vec(&doc).unwrap_or_else(|e| panic!("{e}"));
    parse_document(std::path::Path::new("fixture"), &bytes).unwrap_or_else(|e| panic!("{e}"))
}
