//! ChArUco faces on real photos (issue 33, acceptance 3), against OpenCV's ChArUco detector
//! (`tests/peers/charuco_opencv.py`) on the same photos:
//!
//! - `../shared/datasets/pycalib_charuco_wide`: a 17 × 8 corner board on a monitor through a ~106°
//!   lens (`fixtures/rigs/pycalib_charuco_wide.toml`);
//! - `../shared/datasets/pycamset_charuco_cube_cam0`: pyCamSet's 40 mm ChArUco cube, faces cut by the
//!   frame and at grazing angles (`fixtures/rigs/pycamset_ccube.toml`, derived from pyCamSet's
//!   definition by `scripts/pycamset_ccube_rig.py`).
//!
//! A label differs when OpenCV's corner of a face and id lies nearer to another of cubecal's corners
//! than to the one cubecal gives that face and id; otherwise the two only differ in accuracy (on the
//! cube's grazing faces OpenCV's corners lie up to 4.7 px from cubecal's, and fit the face's
//! homography worse: median RMS 0.68 px against cubecal's 0.54, cubecal better on 38 of 41 faces). The photos are missing → the test fails. The OpenCV parts need python3 with cv2.aruco;
//! without it they are skipped with a message, unless `CUBECAL_REQUIRE_TOOLS=1`.
#![allow(clippy::print_stderr)]

#[path = "support/aruco.rs"]
mod aruco;

use std::collections::HashMap;
use std::ffi::OsStr;
use std::path::{Path, PathBuf};

use aruco::{python_with_aruco, run_peer};
use cubecal::calib::{self, Correspondence, SolveOptions, View};
use cubecal::camera::DistortionModel;
use cubecal::detect::{CornerFinder, detect};
use cubecal::rig::Rig;
use cubecal::rig::charuco::opencv_corner_id;
use nalgebra::{Vector2, Vector3};

fn manifest() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn photos(set: &str) -> Vec<PathBuf> {
    let dir = manifest()
        .join("../shared/datasets")
        .join(set)
        .join("images");
    let mut out: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e} (the dataset is required)", dir.display()))
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "jpg"))
        .collect();
    out.sort();
    assert!(!out.is_empty(), "{}: no photos", dir.display());
    out
}

/// Per photo: (face index, OpenCV corner id) → image position.
type Labels = Vec<HashMap<(usize, usize), Vector2<f64>>>;

fn ours(rig: &Rig, photos: &[PathBuf]) -> Labels {
    let mut finder = CornerFinder::new().unwrap_or_else(|e| panic!("{e}"));
    photos
        .iter()
        .map(|p| {
            let img = image::open(p)
                .unwrap_or_else(|e| panic!("{}: {e}", p.display()))
                .to_luma8();
            let det = detect(&mut finder, &img, rig).unwrap_or_else(|e| panic!("{e}"));
            let mut m = HashMap::new();
            for f in &det.faces {
                let face = &rig.faces[f.face];
                for c in &f.corners {
                    m.insert(
                        (f.face, opencv_corner_id(face.cols, face.rows, c.row, c.col)),
                        c.uv,
                    );
                }
            }
            m
        })
        .collect()
}

fn opencv(py: &str, rig: &Rig, photos: &[PathBuf], dir: &Path) -> (String, Labels) {
    let boards: Vec<serde_json::Value> = rig
        .faces
        .iter()
        .filter_map(|f| {
            let ch = f.charuco.as_ref()?;
            Some(
                serde_json::json!({"name": f.name, "dictionary": ch.dictionary.name(),
                "squares": [f.cols + 1, f.rows + 1], "square": f.square_mm,
                "marker": ch.marker_mm, "ids": ch.ids}),
            )
        })
        .collect();
    let spec = dir.join("boards.json");
    std::fs::write(&spec, serde_json::json!({"boards": boards}).to_string())
        .unwrap_or_else(|e| panic!("{e}"));
    let mut args = vec![spec.into_os_string()];
    args.extend(photos.iter().map(|p| p.clone().into_os_string()));
    let v: serde_json::Value =
        serde_json::from_slice(&run_peer(py, &args)).unwrap_or_else(|e| panic!("{e}"));
    let labels = v["images"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|im| {
            let mut m = HashMap::new();
            for (fi, face) in rig.faces.iter().enumerate() {
                for c in im["boards"][&face.name].as_array().into_iter().flatten() {
                    let id = c[0].as_u64().unwrap_or(u64::MAX) as usize;
                    let uv = Vector2::new(
                        c[1].as_f64().unwrap_or(f64::NAN),
                        c[2].as_f64().unwrap_or(f64::NAN),
                    );
                    m.insert((fi, id), uv);
                }
            }
            m
        })
        .collect();
    (v["cv2"].as_str().unwrap_or("?").to_string(), labels)
}

/// (corners OpenCV labels, of those labelled by cubecal too, labels that differ, cubecal's extra).
/// A label differs when the cubecal corner nearest to OpenCV's is not the one cubecal gives the
/// same face and id.
fn compare(ours: &Labels, cv: &Labels) -> (usize, usize, usize, usize) {
    let (mut n_cv, mut both, mut differ, mut extra) = (0, 0, 0, 0);
    for (o, c) in ours.iter().zip(cv) {
        for (key, uv) in c {
            n_cv += 1;
            if let Some(mine) = o.get(key) {
                both += 1;
                let d = (mine - uv).norm();
                if o.values().any(|other| (other - uv).norm() < d) {
                    differ += 1;
                }
            }
        }
        extra += o.keys().filter(|k| !c.contains_key(k)).count();
    }
    (n_cv, both, differ, extra)
}

/// Acceptance 3, the wide-angle board: every corner OpenCV labels is labelled the same by cubecal
/// (all but the few beside markers cubecal does not decode), and the calibration on the same corners
/// (rational model) agrees with OpenCV's within 3σ.
#[test]
fn pycalib_wide_board_labels_and_calibration_agree_with_opencv() {
    let (rig, _) = Rig::load(&manifest().join("fixtures/rigs/pycalib_charuco_wide.toml"))
        .unwrap_or_else(|e| panic!("{e}"));
    let photos = photos("pycalib_charuco_wide");
    let mine = ours(&rig, &photos);
    let total: usize = mine.iter().map(HashMap::len).sum();
    eprintln!("cubecal: {total} corners in {} photos", photos.len());
    // 1224 measured (OpenCV 5.0's CharucoDetector labels 1220, 4.6 994).
    assert!(total >= 1200, "only {total} corners");
    let Some(py) = python_with_aruco() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let (version, cv) = opencv(&py, &rig, &photos, tmp.path());
    let (n_cv, both, differ, extra) = compare(&mine, &cv);
    eprintln!(
        "OpenCV {version}: {n_cv} corners; cubecal labels {both} of them, {differ} differently; {extra} more"
    );
    assert_eq!(differ, 0, "labels differ from OpenCV's");
    // Measured: 994 of 4.6's 994 (981 before the second threshold pass), 1211 of 5.0's 1220 before
    // it (the rest beside 3 markers cubecal did not decode in one photo; not measured since).
    assert!(
        both as f64 >= 0.98 * n_cv as f64,
        "cubecal labels only {both} of OpenCV's {n_cv} corners"
    );

    // Calibrations on the corners both label: cubecal's solve on cubecal's positions, OpenCV's
    // calibrateCamera on OpenCV's.
    let board = &rig.faces[0];
    let xyz = |id: usize| -> Vector3<f64> {
        let (x, y) = (id % board.cols, id / board.cols);
        board.corner_xyz(board.rows - 1 - y, x)
    };
    let (views, cv_views): (Vec<View>, Vec<serde_json::Value>) = mine
        .iter()
        .zip(&cv)
        .enumerate()
        .filter_map(|(k, (o, c))| common_view(o, c, 0, 6, &xyz, format!("{k}")))
        .unzip();
    // The rational model as the reference used; on OpenCV 4.6's corners (none near the frame's
    // edges) cubecal finds k4…k6 undetermined and refuses, where OpenCV returns a value: then both
    // hold k4, k5, k6 at 0.
    let mut opts = SolveOptions {
        model: DistortionModel::Brown8,
        ..SolveOptions::default()
    };
    let cal = match calib::solve(&views, [1280, 720], &opts) {
        Ok(cal) => cal,
        Err(e) => {
            eprintln!("brown8: {e}; again with k4, k5, k6 held at 0");
            opts.fix.k4 = true;
            opts.fix.k5 = true;
            opts.fix.k6 = true;
            calib::solve(&views, [1280, 720], &opts).unwrap_or_else(|e| panic!("{e}"))
        }
    };
    let spec = serde_json::json!({"image_size": [1280, 720], "rational": true,
        "fix_k456": opts.fix.k4, "views": cv_views});
    agrees_with_opencv(&py, tmp.path(), &spec, &cal);
}

/// The corners of face `fi` that both cubecal (`o`) and OpenCV (`c`) label in one photo, when there
/// are at least `min`: cubecal's positions as a calibration view, OpenCV's as a view of the peer's
/// `--calibrate` (both at `xyz` of the OpenCV corner id).
fn common_view(
    o: &HashMap<(usize, usize), Vector2<f64>>,
    c: &HashMap<(usize, usize), Vector2<f64>>,
    fi: usize,
    min: usize,
    xyz: &dyn Fn(usize) -> Vector3<f64>,
    name: String,
) -> Option<(View, serde_json::Value)> {
    let mut ids: Vec<usize> = c
        .keys()
        .filter(|key| key.0 == fi && o.contains_key(key))
        .map(|key| key.1)
        .collect();
    ids.sort_unstable();
    if ids.len() < min {
        return None;
    }
    let view = View {
        name,
        points: ids
            .iter()
            .map(|&id| Correspondence::new(xyz(id), o[&(fi, id)]))
            .collect(),
    };
    let p: Vec<[f64; 3]> = ids.iter().map(|&id| xyz(id).into()).collect();
    let uv: Vec<[f64; 2]> = ids.iter().map(|&id| c[&(fi, id)].into()).collect();
    Some((view, serde_json::json!({"xyz": p, "uv": uv})))
}

/// OpenCV's calibrateCamera on `spec` (see tests/peers/charuco_opencv.py `--calibrate`), printed
/// beside `cal`; fx, fy, cx, cy must agree within 3 of cubecal's σ.
fn agrees_with_opencv(py: &str, dir: &Path, spec: &serde_json::Value, cal: &calib::Calibration) {
    let path = dir.join("views.json");
    std::fs::write(&path, spec.to_string()).unwrap_or_else(|e| panic!("{e}"));
    let cvcal: serde_json::Value = serde_json::from_slice(&run_peer(
        py,
        &[OsStr::new("--calibrate"), path.as_os_str()],
    ))
    .unwrap_or_else(|e| panic!("{e}"));
    eprintln!(
        "cubecal RMS {:.3} px per coordinate, OpenCV RMS {:.3} px (√2 × per coordinate)",
        cal.rms_px,
        cvcal["rms"].as_f64().unwrap_or(f64::NAN)
    );
    let cam = &cal.camera;
    let ours4 = [cam.fx(), cam.fy(), cam.cx(), cam.cy()];
    for (i, name) in ["fx", "fy", "cx", "cy"].iter().enumerate() {
        let theirs = cvcal["K"][i].as_f64().unwrap_or(f64::NAN);
        let sigma = cal.std_dev[i];
        eprintln!(
            "{name}: cubecal {:.3} ± {sigma:.3}, OpenCV {theirs:.3} ± {:.3} ({:.2} σ)",
            ours4[i],
            cvcal["sigma"][i].as_f64().unwrap_or(f64::NAN),
            (ours4[i] - theirs).abs() / sigma
        );
        assert!(
            (ours4[i] - theirs).abs() <= 3.0 * sigma,
            "{name}: {:.3} vs OpenCV's {theirs:.3}, more than 3σ ({sigma:.3}) apart",
            ours4[i]
        );
    }
}

/// Acceptance 3, the cube: every corner OpenCV labels is labelled by cubecal, none differently,
/// and cubecal labels at least as many corners in all; and the calibration on the corners both
/// label agrees with OpenCV's within 3σ. The calibrations take each face of each photo as a planar
/// view of its own (face coordinates): the printed cube is not the nominal one (its faces sit up to
/// 0.7 mm and 0.9° off: `calibrate --refine-rig`), which a calibration on the cube's nominal 3D
/// geometry would charge to the camera, and OpenCV's calibrateCamera takes no 3D rig without an
/// initial camera.
#[test]
fn pycamset_cube_labels_agree_with_opencv() {
    let (rig, _) = Rig::load(&manifest().join("fixtures/rigs/pycamset_ccube.toml"))
        .unwrap_or_else(|e| panic!("{e}"));
    let photos = photos("pycamset_charuco_cube_cam0");
    let mine = ours(&rig, &photos);
    let total: usize = mine.iter().map(HashMap::len).sum();
    eprintln!("cubecal: {total} corners in {} photos", photos.len());
    let Some(py) = python_with_aruco() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let (version, cv) = opencv(&py, &rig, &photos, tmp.path());
    let (n_cv, both, differ, extra) = compare(&mine, &cv);
    eprintln!(
        "OpenCV {version}: {n_cv} corners; cubecal labels {both} of them, {differ} differently; {extra} more"
    );
    assert_eq!(differ, 0, "labels differ from OpenCV's");
    assert!(total >= n_cv, "{total} corners, OpenCV {n_cv}");
    // Measured with OpenCV 4.6: all 2186 (2130 before the second threshold pass of
    // `charuco::marker_candidates`, 2173 before the corner fit in the white gaps, `fit_in_gaps`,
    // 2179 before markers were read where their decoded neighbours predict them,
    // `charuco::predicted_markers`: 232 of 13.jpg face 4 and 124 of 17.jpg face 2, misread, 133 and
    // 138 of 14.jpg face 2, split into two regions each).
    assert_eq!(
        both,
        n_cv,
        "cubecal leaves {} of OpenCV's {n_cv} corners unlabelled (none measured)",
        n_cv - both
    );

    let mut views = Vec::new();
    let mut cv_views = Vec::new();
    for (k, (o, c)) in mine.iter().zip(&cv).enumerate() {
        for (fi, face) in rig.faces.iter().enumerate() {
            if let Some((v, cv_v)) = common_view(
                o,
                c,
                fi,
                8,
                &face_xyz(&rig, fi),
                format!("{k}/{}", face.name),
            ) {
                views.push(v);
                cv_views.push(cv_v);
            }
        }
    }
    let image_size = [1920, 1080];
    let cal = calib::solve(&views, image_size, &SolveOptions::default())
        .unwrap_or_else(|e| panic!("{e}"));
    eprintln!("{} face views", views.len());
    missed_against_camera(&rig, &photos, &mine, &cv, image_size);
    let spec = serde_json::json!({"image_size": image_size, "rational": false, "views": cv_views});
    agrees_with_opencv(&py, tmp.path(), &spec, &cal);
}

/// Face coordinates (mm) of OpenCV corner `id` of face `fi`.
fn face_xyz(rig: &Rig, fi: usize) -> impl Fn(usize) -> Vector3<f64> + '_ {
    let face = &rig.faces[fi];
    move |id: usize| {
        let (col, row) = (id % face.cols, face.rows - 1 - id / face.cols);
        Vector3::new(
            col as f64 * face.square_mm,
            row as f64 * face.square_mm,
            0.0,
        )
    }
}

/// Whether OpenCV's corners that cubecal does not label are where the camera puts them. Cameras
/// solved on the corners both label (face views of at least 8, as for the comparison), once on
/// cubecal's positions and once on OpenCV's; per face with such corners, its pose in each camera
/// from that detector's other corners of the face; per corner, the distance of OpenCV's position from
/// its projection, beside the same for OpenCV's other corners of the face (median, largest) and a
/// square's side there.
fn missed_against_camera(
    rig: &Rig,
    photos: &[PathBuf],
    mine: &Labels,
    cv: &Labels,
    image_size: [u32; 2],
) {
    let face_view = |labels: &HashMap<(usize, usize), Vector2<f64>>,
                     fi: usize,
                     keep: &dyn Fn(usize) -> bool| {
        let mut ids: Vec<usize> = labels
            .keys()
            .filter(|key| key.0 == fi && keep(key.1))
            .map(|key| key.1)
            .collect();
        ids.sort_unstable();
        let xyz = face_xyz(rig, fi);
        View {
            name: format!("face {fi}"),
            points: ids
                .iter()
                .map(|&id| Correspondence::new(xyz(id), labels[&(fi, id)]))
                .collect(),
        }
    };
    let mut views: [Vec<View>; 2] = [Vec::new(), Vec::new()];
    for (k, (o, c)) in mine.iter().zip(cv).enumerate() {
        for fi in 0..rig.faces.len() {
            let common = |id: usize| o.contains_key(&(fi, id)) && c.contains_key(&(fi, id));
            let (mut ov, mut cvv) = (face_view(o, fi, &common), face_view(c, fi, &common));
            ov.name = format!("{k}/{fi}");
            cvv.name.clone_from(&ov.name);
            if ov.points.len() >= 8 {
                views[0].push(ov);
                views[1].push(cvv);
            }
        }
    }
    let cams = views.map(|v| {
        calib::solve(&v, image_size, &SolveOptions::default())
            .unwrap_or_else(|e| panic!("{e}"))
            .camera
    });
    for (k, (o, c)) in mine.iter().zip(cv).enumerate() {
        let name = photos[k]
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let mut missed: Vec<(usize, usize)> = c
            .keys()
            .filter(|key| !o.contains_key(key))
            .copied()
            .collect();
        missed.sort_unstable();
        for &(fi, id) in &missed {
            let xyz = face_xyz(rig, fi);
            let other = |i: usize| !missed.contains(&(fi, i));
            let line = |cam: &cubecal::camera::Camera,
                        labels: &HashMap<(usize, usize), Vector2<f64>>| {
                let fit = match calib::pose::solve_pose(cam, &face_view(labels, fi, &other)) {
                    Ok(fit) => fit,
                    Err(e) => return format!("no pose ({e})"),
                };
                let pose = &fit.cam_from_rig;
                let at = |id: usize| cam.project(pose, &xyz(id)).ok();
                let d = |id: usize| at(id).map_or(f64::NAN, |p| (p - c[&(fi, id)]).norm());
                let mut others: Vec<f64> = c
                    .keys()
                    .filter(|kk| kk.0 == fi && other(kk.1))
                    .map(|kk| d(kk.1))
                    .collect();
                others.sort_by(f64::total_cmp);
                let s = rig.faces[fi].square_mm;
                let side = |dx: f64, dy: f64| {
                    let q = cam
                        .project(pose, &(xyz(id) + Vector3::new(dx, dy, 0.0)))
                        .ok();
                    match (at(id), q) {
                        (Some(p), Some(q)) => (p - q).norm(),
                        _ => f64::NAN,
                    }
                };
                format!(
                    "{:.2} px (others median {:.2}, max {:.2}; square {:.0} × {:.0} px)",
                    d(id),
                    others.get(others.len() / 2).copied().unwrap_or(f64::NAN),
                    others.last().copied().unwrap_or(f64::NAN),
                    side(s, 0.0),
                    side(0.0, s),
                )
            };
            eprintln!(
                "{name} face {fi} id {id}: OpenCV's corner from cubecal's camera and corners {}; from OpenCV's {}",
                line(&cams[0], o),
                line(&cams[1], c)
            );
        }
    }
}
