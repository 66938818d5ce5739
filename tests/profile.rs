//! The profile store against the issue's acceptance lines: history and Δσ, rejected runs and rollback,
//! hostile identities, injected disk-full errors, two writers, SIGKILL crash safety, and the exports
//! loaded by OpenCV, ROS's parser and mrcal.
//!
//! Tests that need a second process re-run this test binary with `CUBECAL_PROFILE_CHILD` set: the
//! `child_*` tests do nothing unless that variable names them.
//!
//! Printing is allowed here: children talk to their parent over stdout, and the tests print the figures
//! they measure (run with `--nocapture` to see them).
#![allow(clippy::print_stdout, clippy::print_stderr)]

use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use cubecal::calib::init::InitMethod;
use cubecal::calib::report::{CalibrationReport, DistortionReport};
use cubecal::camera::{Camera, DistortionModel};
use cubecal::profile::export;
use cubecal::profile::store::{self, folder_name};
use cubecal::profile::{
    CommitOptions, Identity, IdentityOrigin, Profile, ProfileError, RigRef, Store,
    identity_from_bytes, read_document, rfc3339_from_unix,
};
use cubecal::station::{Check, Verdict};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

const CHILD_VAR: &str = "CUBECAL_PROFILE_CHILD";
const DIR_VAR: &str = "CUBECAL_PROFILE_DIR";

// ---------------------------------------------------------------------------------------------------
// fixtures

fn report(camera: &Camera, sigma: f64) -> CalibrationReport {
    let k = camera.k_matrix();
    // σ and covariance under the names the solver gives them (kb4's coefficients are k1, k2, k3, k4)
    let names: Vec<&str> = ["fx", "fy", "cx", "cy"]
        .into_iter()
        .chain(camera.model.coefficient_names())
        .collect();
    let n = names.len();
    CalibrationReport {
        image_size: camera.image_size,
        camera_matrix: [
            [k[(0, 0)], k[(0, 1)], k[(0, 2)]],
            [k[(1, 0)], k[(1, 1)], k[(1, 2)]],
            [k[(2, 0)], k[(2, 1)], k[(2, 2)]],
        ],
        distortion: DistortionReport {
            model: camera.model.name().to_string(),
            coefficients: camera.distortion_coefficients(),
        },
        std_dev: names.iter().map(|s| (s.to_string(), sigma)).collect(),
        free_params: names.iter().map(|s| s.to_string()).collect(),
        covariance: (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| if i == j { sigma * sigma } else { 0.0 })
                    .collect()
            })
            .collect(),
        rms_px: 0.1,
        rms_reprojection_px: 0.1 * 2f64.sqrt(),
        sigma_px: 0.1,
        noise_scale: None,
        n_points: 1000,
        n_params: n + 60,
        views: vec![],
        iterations: 7,
        termination: "converged".into(),
        converged: true,
        init_method: InitMethod::Dlt,
    }
}

fn camera(fx: f64) -> Camera {
    Camera::pinhole([1280, 960], fx, fx * 1.001, 639.5, 479.5)
        .with_distortion(DistortionModel::Brown5, &[-0.3, 0.1, 0.001, -0.0008, -0.01])
}

fn verdict(pass: bool) -> Verdict {
    Verdict::from_checks(vec![Check::at_most(
        "rms_px",
        if pass { 0.1 } else { 0.9 },
        0.5,
        || "refocus".into(),
    )])
}

/// Version `n` of a camera's profile: fx = 1000 + n/1000 (σ 0.5), created n seconds after a fixed time.
fn profile(identity: &str, n: u64, pass: bool) -> Profile {
    Profile {
        identity: Identity {
            id: identity.to_string(),
            origin: IdentityOrigin::User,
            device: None,
        },
        calibration: report(&camera(1000.0 + n as f64 / 1000.0), 0.5),
        verdict: verdict(pass),
        controls: vec![],
        format: None,
        rig: RigRef {
            name: "cube_outside".into(),
            sha256: "0".repeat(64),
        },
        session: None,
        software_version: env!("CARGO_PKG_VERSION").into(),
        created: rfc3339_from_unix(1_790_000_000 + n),
        change: None,
    }
}

/// The version number a profile of [`profile`] was built from (fx − 1000 in thousandths).
fn version_of(p: &Profile) -> u64 {
    ((p.calibration.camera_matrix[0][0] - 1000.0) * 1000.0).round() as u64
}

fn opts() -> CommitOptions {
    CommitOptions { jump_sigma: 5.0 }
}

/// `f` (a store call that takes the lock) for tests that are not about the lock: a Busy here is
/// not the store's doing. Another test of this process may have forked a child while one of our
/// calls held the lock, and until that child execs it keeps a copy of the lock's file description
/// (flock belongs to the description, not the process), so our next call finds the lock taken.
/// Seen under heavy load in stops 25 and 26. The tests of Busy itself call the store directly.
fn unless_busy<T>(mut f: impl FnMut() -> Result<T, ProfileError>) -> Result<T, ProfileError> {
    let mut tries = 0;
    loop {
        match f() {
            Err(ProfileError::Busy { .. }) if tries < 40 => {
                tries += 1;
                std::thread::sleep(Duration::from_millis(50));
            }
            r => return r,
        }
    }
}

/// `store.commit` with [`unless_busy`].
fn commit(
    store: &Store,
    profile: &Profile,
) -> Result<cubecal::profile::CommitOutcome, ProfileError> {
    unless_busy(|| store.commit(profile, &opts()))
}

fn tempdir() -> tempfile::TempDir {
    tempfile::tempdir().unwrap_or_else(|e| panic!("temp dir: {e}"))
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Every file under `dir` (recursively).
fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap_or_else(|e| panic!("{}: {e}", d.display())) {
            let p = e.unwrap_or_else(|e| panic!("{e}")).path();
            if p.is_dir() {
                todo.push(p);
            } else {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// Re-run this test binary as a child running only the test `name`.
fn child(name: &str, dir: &Path) -> Command {
    let exe = std::env::current_exe().unwrap_or_else(|e| panic!("current_exe: {e}"));
    let mut cmd = Command::new(exe);
    cmd.args([name, "--exact", "--nocapture", "--test-threads=1"])
        .env(CHILD_VAR, name)
        .env(DIR_VAR, dir);
    cmd
}

fn is_child(name: &str) -> Option<PathBuf> {
    (std::env::var(CHILD_VAR).ok().as_deref() == Some(name))
        .then(|| std::env::var_os(DIR_VAR).map(PathBuf::from))
        .flatten()
}

// ---------------------------------------------------------------------------------------------------
// history, change, versions

#[test]
fn commits_keep_history_and_measure_the_change_in_sigma() {
    let tmp = tempdir();
    let store = Store::open(&tmp.path().join("store")).unwrap_or_else(|e| panic!("{e}"));
    let id = "usb:046d:0825:A1B2C3";
    let first = commit(&store, &profile(id, 0, true)).unwrap_or_else(|e| panic!("{e}"));
    assert!(first.archived.is_none() && first.change.is_none() && !first.jump);
    let first_bytes = read(&first.current);

    // fx moves by 1/1000 px with σ 0.5 on both sides: Δ/σ = 0.001/√(0.5²+0.5²)
    let second = commit(&store, &profile(id, 1, true)).unwrap_or_else(|e| panic!("{e}"));
    let archived = second
        .archived
        .clone()
        .unwrap_or_else(|| panic!("no archive"));
    assert_eq!(
        read(&archived),
        first_bytes,
        "history holds the replaced document verbatim"
    );
    let change = second.change.clone().unwrap_or_else(|| panic!("no change"));
    let fx = change.params.iter().find(|p| p.name == "fx");
    let fx = fx.unwrap_or_else(|| panic!("no fx in {change:?}"));
    assert!((fx.delta - 0.001).abs() < 1e-9, "{fx:?}");
    assert!(
        (fx.delta_sigma - 0.001 / 0.5f64.hypot(0.5)).abs() < 1e-9,
        "{fx:?}"
    );
    assert!(!second.jump && !change.jump);
    assert_eq!(change.previous_sha256, store::sha256_hex(&first_bytes));
    let stored = read_document(&second.current).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(stored.change, Some(change));

    // fx moves by 5 px = 7.07 σ > 5: a jump, still stored
    let third = commit(&store, &profile(id, 5000, true)).unwrap_or_else(|e| panic!("{e}"));
    let change = third.change.clone().unwrap_or_else(|| panic!("no change"));
    assert!(third.jump && change.jump, "{change:?}");
    let fx = change.params.iter().find(|p| p.name == "fx");
    let fx = fx.unwrap_or_else(|| panic!("no fx in {change:?}"));
    assert!(
        (fx.delta_sigma - 4.999 / 0.5f64.hypot(0.5)).abs() < 1e-6,
        "{fx:?}"
    );
    // fy = 1.001·fx moves a little more, and is the largest
    assert!((change.max_abs_delta_sigma - 4.999 * 1.001 / 0.5f64.hypot(0.5)).abs() < 1e-6);
    assert_eq!(store.history(id).map(|h| h.len()).ok(), Some(2));

    // a changed image size is a jump whatever the numbers
    let mut resized = profile(id, 5000, true);
    resized.calibration.image_size = [640, 480];
    let out = commit(&store, &resized).unwrap_or_else(|e| panic!("{e}"));
    assert!(out.jump);
    assert_eq!(
        out.change.map(|c| c.notes.len()),
        Some(1),
        "the note says why"
    );
}

/// The fisheye of issue 32: fx ≈ 350 at 1280×960, Kannala–Brandt in OpenCV's `cv::fisheye` order.
fn kb4_camera() -> Camera {
    Camera::pinhole([1280, 960], 350.4, 349.7, 641.3, 478.6)
        .with_distortion(DistortionModel::Kb4, &[0.021, -0.0043, 0.00052, -0.000047])
}

#[test]
fn a_kb4_profile_round_trips_through_the_store_and_its_diff_names_k1_to_k4() {
    let tmp = tempdir();
    let root = tmp.path().join("store");
    let store = Store::open(&root).unwrap_or_else(|e| panic!("{e}"));
    let id = "usb:2bdf:0280:FISHEYE";
    let mut v1 = profile(id, 0, true);
    v1.calibration = report(&kb4_camera(), 1e-5);
    let first = commit(&store, &v1).unwrap_or_else(|e| panic!("{e}"));
    let stored = read_document(&first.current).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(stored, v1, "the document reads back as written");
    let json: serde_json::Value =
        serde_json::from_slice(&read(&first.current)).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(json["calibration"]["distortion"]["model"], "kb4");
    assert_eq!(
        json["calibration"]["distortion"]["coefficients"],
        serde_json::json!([0.021, -0.0043, 0.00052, -0.000047])
    );

    // k3 moves by 4σ and k4 by 1σ: the change names them k3 and k4 (not OpenCV's p1 and p2, whose
    // slots kb4 does not use) and compares them with their own σ
    let mut v2 = v1.clone();
    v2.created = rfc3339_from_unix(1_790_000_100);
    v2.calibration.distortion.coefficients[2] += 4e-5 * 2f64.sqrt();
    v2.calibration.distortion.coefficients[3] += 1e-5 * 2f64.sqrt();
    let second = commit(&store, &v2).unwrap_or_else(|e| panic!("{e}"));
    let change = second.change.unwrap_or_else(|| panic!("no change"));
    let names: Vec<&str> = change.params.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, ["fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"]);
    let by_name = |n: &str| {
        change
            .params
            .iter()
            .find(|p| p.name == n)
            .map(|p| p.delta_sigma)
    };
    assert!(
        (by_name("k3").unwrap_or(f64::NAN) - 4.0).abs() < 1e-6,
        "{change:?}"
    );
    assert!(
        (by_name("k4").unwrap_or(f64::NAN) - 1.0).abs() < 1e-6,
        "{change:?}"
    );
    assert!(!change.jump && change.notes.is_empty(), "{change:?}");

    // a brown5 profile replacing it is a changed model: a jump, said in a note
    let third = commit(&store, &profile(id, 0, true)).unwrap_or_else(|e| panic!("{e}"));
    let change = third.change.unwrap_or_else(|| panic!("no change"));
    assert!(change.jump);
    assert_eq!(
        change.notes,
        ["distortion model changed from kb4 to brown5"],
        "{change:?}"
    );

    // `profile show` of the kb4 version in history names the coefficients with their σ
    let history = store.history(id).unwrap_or_else(|e| panic!("{e}"));
    let out = cubecal(&["profile", "show", &history[1].to_string_lossy()], &root);
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(0), "{text}");
    assert!(
        text.contains("distortion: kb4 k1 0.021000 ± 0.000010, k2 -0.004300 ± 0.000010, k3 0.000577 ± 0.000010, k4 -0.000033 ± 0.000010"),
        "{text}"
    );

    // its exports from the command line: kalibr written, mrcal refused whole, naming the model
    let file = history[1].to_string_lossy().into_owned();
    let out = cubecal(&["profile", "export", &file, "--format", "kalibr"], &root);
    assert_eq!(out.status.code(), Some(0));
    assert_eq!(
        String::from_utf8_lossy(&out.stdout),
        export::kalibr_camchain_yaml(&v2).unwrap_or_else(|e| panic!("{e}"))
    );
    let out = cubecal(&["profile", "export", &file, "--format", "mrcal"], &root);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{err}");
    assert!(
        err.starts_with("error: cannot export to mrcal: the kb4 lens (Kannala–Brandt")
            && err.ends_with("use opencv, ros, colmap or kalibr\n"),
        "{err}"
    );
}

#[test]
fn a_newer_format_version_is_refused_not_misread() {
    let tmp = tempdir();
    let store = Store::open(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
    let out = commit(&store, &profile("cam", 0, true)).unwrap_or_else(|e| panic!("{e}"));
    let text = String::from_utf8(read(&out.current)).unwrap_or_default();
    assert!(text.starts_with("{\n  \"format_version\": 1,"), "{text}");
    let newer = text.replacen("\"format_version\": 1", "\"format_version\": 2", 1);
    std::fs::write(&out.current, newer).unwrap_or_else(|e| panic!("{e}"));
    match read_document(&out.current) {
        Err(ProfileError::NewerVersion {
            found: 2,
            supported: 1,
            ..
        }) => {}
        other => panic!("expected NewerVersion, got {other:?}"),
    }
    // and a commit does not overwrite what it cannot read
    let before = read(&out.current);
    assert!(matches!(
        commit(&store, &profile("cam", 1, true)),
        Err(ProfileError::NewerVersion { .. })
    ));
    assert_eq!(read(&out.current), before);
}

#[test]
fn invalid_profiles_are_refused_before_anything_is_written() {
    let tmp = tempdir();
    let store = Store::open(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
    let mut bad = vec![];
    let mut p = profile("", 0, true);
    bad.push(p.clone());
    p = profile("cam", 0, true);
    p.created = "yesterday".into();
    bad.push(p.clone());
    p = profile("cam", 0, true);
    p.calibration.camera_matrix[0][0] = f64::NAN;
    bad.push(p.clone());
    p = profile("cam", 0, true);
    p.calibration.std_dev.insert("fx".into(), f64::INFINITY);
    bad.push(p.clone());
    p = profile("cam", 0, true);
    p.calibration.distortion.coefficients.pop();
    bad.push(p);
    for p in bad {
        match commit(&store, &p) {
            Err(ProfileError::Invalid { .. }) => {}
            other => panic!("expected Invalid, got {other:?}"),
        }
    }
    assert!(
        files_under(tmp.path())
            .iter()
            .all(|f| !f.ends_with(store::CURRENT)),
        "no profile written"
    );
}

// ---------------------------------------------------------------------------------------------------
// acceptance 4: rejected run, rollback

#[test]
fn a_rejected_run_leaves_the_passing_profile_byte_identical_and_rollback_restores_the_previous() {
    let tmp = tempdir();
    let store = Store::open(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
    let id = "usb:1234:5678:SN1";
    let v1 = commit(&store, &profile(id, 1, true)).unwrap_or_else(|e| panic!("{e}"));
    let v1_bytes = read(&v1.current);
    let v2 = commit(&store, &profile(id, 2, true)).unwrap_or_else(|e| panic!("{e}"));
    let v2_bytes = read(&v2.current);
    let files_before: Vec<(PathBuf, Vec<u8>)> = files_under(tmp.path())
        .into_iter()
        .map(|f| (f.clone(), read(&f)))
        .collect();

    match commit(&store, &profile(id, 3, false)) {
        Err(e @ ProfileError::Rejected { .. }) => {
            assert_eq!(e.exit_code(), cubecal::exit::QA_REJECTED);
            assert!(e.to_string().contains("rms_px"), "{e}");
        }
        other => panic!("expected Rejected, got {other:?}"),
    }
    let files_after: Vec<(PathBuf, Vec<u8>)> = files_under(tmp.path())
        .into_iter()
        .map(|f| (f.clone(), read(&f)))
        .collect();
    assert_eq!(files_after, files_before, "nothing in the store changed");
    assert_eq!(read(&v2.current), v2_bytes);

    let back = unless_busy(|| store.rollback(id)).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        read(&v2.current),
        v1_bytes,
        "rollback restores v1 byte for byte"
    );
    assert_eq!(read(&back.set_aside), v2_bytes, "v2 is kept aside");
    assert_eq!(back.restored_created, profile(id, 1, true).created);
    assert!(matches!(
        unless_busy(|| store.rollback(id)),
        Err(ProfileError::NoHistory { .. })
    ));
    // the folder name works as DEVICE too
    let (p, _) = store
        .current(&folder_name(id))
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(version_of(&p), 1);
}

// ---------------------------------------------------------------------------------------------------
// acceptance 3: hostile identities

fn hostile_identities() -> Vec<String> {
    vec![
        "../../../../etc/passwd".into(),
        "/absolute/path".into(),
        "..".into(),
        ".".into(),
        "".into(), // refused: an empty identity
        "a/b".into(),
        "a_b".into(), // sanitises like "a/b"
        "nul\0inside".into(),
        "nul_inside".into(),
        "newline\nand\rcarriage\x1b[31mred".into(),
        "tab\there".into(),
        "x".repeat(4096),
        format!("{}y", "x".repeat(4095)),
        identity_from_bytes(b"bad\xff\xfeutf8"),
        identity_from_bytes(b"bad\xfe\xffutf8"),
        "usb:046d:0825:\u{202e}reversed".into(),
        "unicode-é-漢字".into(),
        "CON".into(),
        "-rf".into(),
        // looks like the folder of "a/b": must still name its own camera
        folder_name("a/b"),
    ]
}

#[test]
fn hostile_identities_stay_inside_the_store_in_distinct_folders_and_list_escaped() {
    let tmp = tempdir();
    let root = tmp.path().join("store");
    let store = Store::open(&root).unwrap_or_else(|e| panic!("{e}"));
    let ids = hostile_identities();
    let mut stored = Vec::new();
    for (n, id) in ids.iter().enumerate() {
        match commit(&store, &profile(id, n as u64, true)) {
            Ok(out) => {
                assert_eq!(
                    out.folder.parent(),
                    Some(root.as_path()),
                    "{id:?} -> {}",
                    out.folder.display()
                );
                stored.push((id.clone(), out.folder));
            }
            Err(ProfileError::Invalid { field, .. }) if id.is_empty() => {
                assert_eq!(field, "identity.id")
            }
            Err(e) => panic!("{id:?}: {e}"),
        }
    }
    assert!(stored.len() >= 10);
    // nothing outside the store
    let outside: Vec<PathBuf> = files_under(tmp.path())
        .into_iter()
        .filter(|f| !f.starts_with(&root))
        .collect();
    assert!(outside.is_empty(), "{outside:?}");
    // one folder per identity, each a direct child of the root
    let folders: BTreeSet<&PathBuf> = stored.iter().map(|(_, f)| f).collect();
    assert_eq!(folders.len(), stored.len());
    let dirs = std::fs::read_dir(&root)
        .map(|d| d.count())
        .unwrap_or_default();
    assert_eq!(dirs, stored.len());
    // each reads back as itself
    for (id, _) in &stored {
        let (p, _) = store.current(id).unwrap_or_else(|e| panic!("{id:?}: {e}"));
        assert_eq!(&p.identity.id, id);
    }
    let listed = store.list().unwrap_or_else(|e| panic!("{e}"));
    let listed: BTreeSet<String> = listed
        .into_iter()
        .map(|e| {
            e.summary
                .unwrap_or_else(|err| panic!("{}: {err}", e.folder))
                .identity
        })
        .collect();
    let expected: BTreeSet<String> = stored.iter().map(|(id, _)| id.clone()).collect();
    assert_eq!(listed, expected);

    // `cubecal profile list` shows them escaped: no control character reaches the terminal
    let out = Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["profile", "list", "--store"])
        .arg(&root)
        .output()
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap_or_else(|e| panic!("{e}"));
    assert!(
        !text
            .chars()
            .any(|c| c.is_control() && !matches!(c, '\n' | '\t') || c == '\u{202e}'),
        "{text:?}"
    );
    assert!(
        text.contains(r"newline\nand\rcarriage\u{1b}[31mred"),
        "{text}"
    );
    assert!(text.contains(r"nul\0inside"), "{text}");
    assert!(text.contains(r"bad\\xff\\xfeutf8"), "{text}");
    assert_eq!(
        text.lines().count(),
        stored.len() + 1,
        "a header and one line each"
    );
}

// ---------------------------------------------------------------------------------------------------
// acceptance 6: disk full while writing

#[test]
fn a_failed_write_is_a_typed_error_and_leaves_the_previous_profile_intact() {
    let tmp = tempdir();
    let id = "usb:1234:5678:FULL";
    let v1 = Store::open(tmp.path())
        .and_then(|s| commit(&s, &profile(id, 1, true)))
        .unwrap_or_else(|e| panic!("{e}"));
    let v1_bytes = read(&v1.current);
    let len = v1_bytes.len() as u64;
    // Fail at the first, a middle and the last byte of the history copy of v1 (the first write), then
    // once in the new current.json after a complete history copy (budget len + 10), then — the history
    // copy now existing and not rewritten — at the first, a middle and the last byte of current.json
    // (longer than v1: it carries the change).
    for budget in [0, 1, len / 2, len - 1, len + 10, 0, 1, len / 2, len - 1] {
        let store = Store::open(tmp.path())
            .map(|s| s.fail_writes_after(budget))
            .unwrap_or_else(|e| panic!("{e}"));
        let result = commit(&store, &profile(id, 2, true));
        match result {
            Err(e @ ProfileError::Write { .. }) => {
                let io = std::error::Error::source(&e)
                    .and_then(|s| s.downcast_ref::<std::io::Error>())
                    .map(|e| e.kind());
                assert_eq!(io, Some(std::io::ErrorKind::StorageFull), "{e}");
                assert_eq!(e.exit_code(), cubecal::exit::INTERNAL);
            }
            other => panic!("budget {budget}: expected a write error, got {other:?}"),
        }
        assert_eq!(read(&v1.current), v1_bytes, "budget {budget}");
        let stray: Vec<PathBuf> = files_under(tmp.path())
            .into_iter()
            .filter(|f| f.to_string_lossy().contains(".tmp-"))
            .collect();
        assert!(stray.is_empty(), "budget {budget}: {stray:?}");
    }
    // after the failures a normal commit works and history holds v1 once
    let store = Store::open(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
    commit(&store, &profile(id, 2, true)).unwrap_or_else(|e| panic!("{e}"));
    let history = store.history(id).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(history.len(), 1, "{history:?}");
    assert_eq!(read(&history[0]), v1_bytes);
}

// ---------------------------------------------------------------------------------------------------
// acceptance 2: two writers

#[test]
fn child_hold_lock() {
    let Some(dir) = is_child("child_hold_lock") else {
        return;
    };
    let store = Store::open(&dir).unwrap_or_else(|e| panic!("{e}"));
    let _lock = store.lock("usb:1:2:TWO").unwrap_or_else(|e| panic!("{e}"));
    println!("locked");
    let _ = std::io::stdout().flush();
    // hold the lock until the parent closes our stdin
    let mut line = String::new();
    let _ = std::io::stdin().read_line(&mut line);
}

#[test]
fn child_commit_loop() {
    let Some(dir) = is_child("child_commit_loop") else {
        return;
    };
    let store = Store::open(&dir).unwrap_or_else(|e| panic!("{e}"));
    let base: u64 = std::env::var("CUBECAL_PROFILE_BASE")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    let (mut ok, mut busy) = (0, 0);
    for n in 0..40 {
        match store.commit(&profile("usb:1:2:TWO", base + n, true), &opts()) {
            Ok(_) => ok += 1,
            Err(ProfileError::Busy { .. }) => busy += 1,
            Err(e) => panic!("{e}"),
        }
        // a Busy returns at once: pause so that the two writers' attempts interleave
        std::thread::sleep(Duration::from_millis(2));
    }
    println!("ok={ok} busy={busy}");
}

#[test]
fn two_writers_one_gets_busy_and_no_file_is_torn() {
    let tmp = tempdir();
    let store = Store::open(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
    let id = "usb:1:2:TWO";
    let v1 = commit(&store, &profile(id, 1, true)).unwrap_or_else(|e| panic!("{e}"));
    let v1_bytes = read(&v1.current);

    // another process holds the lock: our commit is refused at once with Busy
    let mut holder = child("child_hold_lock", tmp.path())
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{e}"));
    let mut lines = BufReader::new(holder.stdout.take().unwrap_or_else(|| panic!("stdout")));
    let mut line = String::new();
    // the test harness prints "test child_hold_lock ... " before the child's own output, on one line
    while !line.contains("locked") {
        line.clear();
        if lines.read_line(&mut line).unwrap_or(0) == 0 {
            panic!("lock holder exited early");
        }
    }
    let t0 = Instant::now();
    match store.commit(&profile(id, 2, true), &opts()) {
        Err(e @ ProfileError::Busy { .. }) => assert_eq!(e.exit_code(), cubecal::exit::DEVICE),
        other => panic!("expected Busy, got {other:?}"),
    }
    assert!(
        t0.elapsed() < Duration::from_secs(1),
        "Busy without waiting"
    );
    assert_eq!(read(&v1.current), v1_bytes);
    drop(holder.stdin.take());
    let _ = holder.wait();
    // the holder is gone: the lock is free again
    commit(&store, &profile(id, 2, true)).unwrap_or_else(|e| panic!("{e}"));

    // two processes committing the same camera at once: every attempt succeeds or is Busy
    let spawn = |base: u64| {
        child("child_commit_loop", tmp.path())
            .env("CUBECAL_PROFILE_BASE", base.to_string())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("{e}"))
    };
    let (a, b) = (spawn(1000), spawn(2000));
    let mut total_busy = 0;
    let mut total_ok = 0;
    for c in [a, b] {
        let out = c.wait_with_output().unwrap_or_else(|e| panic!("{e}"));
        assert!(out.status.success());
        let text = String::from_utf8_lossy(&out.stdout);
        let line = text
            .lines()
            .find_map(|l| l.split_once("ok=").map(|(_, rest)| rest))
            .unwrap_or_else(|| panic!("{text}"));
        let nums: Vec<u32> = line
            .split(|c: char| !c.is_ascii_digit())
            .filter_map(|s| s.parse().ok())
            .collect();
        total_ok += nums[0];
        total_busy += nums[1];
    }
    println!("two concurrent writers: {total_ok} commits, {total_busy} busy");
    assert_eq!(total_ok + total_busy, 80);
    assert!(total_ok > 0);
    let (p, _) = store.current(id).unwrap_or_else(|e| panic!("{e}"));
    assert!(version_of(&p) >= 1000, "the last commit is from a child");
    for h in store.history(id).unwrap_or_else(|e| panic!("{e}")) {
        read_document(&h).unwrap_or_else(|e| panic!("{e}"));
    }
}

// ---------------------------------------------------------------------------------------------------
// acceptance 1: SIGKILL at random moments

const CRASH_ID: &str = "usb:dead:beef:KILL";

#[test]
fn child_write_forever() {
    let Some(dir) = is_child("child_write_forever") else {
        return;
    };
    let store = Store::open(&dir).unwrap_or_else(|e| panic!("{e}"));
    let mut n = store
        .current(CRASH_ID)
        .map(|(p, _)| version_of(&p) + 1)
        .unwrap_or(1);
    let mut stdout = std::io::stdout();
    loop {
        // say which version is about to be written, so the parent knows every version attempted
        let _ = writeln!(stdout, "V={n}");
        let _ = stdout.flush();
        commit(&store, &profile(CRASH_ID, n, true)).unwrap_or_else(|e| panic!("{e}"));
        n += 1;
    }
}

/// The version in a child's `V=n` line (the harness may print its own text before it).
fn announced(line: &str) -> Option<u64> {
    let (_, rest) = line.rsplit_once("V=")?;
    rest.trim().parse().ok()
}

#[test]
fn sigkill_at_random_moments_never_leaves_a_torn_or_unknown_profile() {
    let tmp = tempdir();
    let store = Store::open(tmp.path()).unwrap_or_else(|e| panic!("{e}"));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(18);
    let kills = 200;
    let mut max_attempted = 0u64;
    let mut last_version = 0u64;
    let mut stray_seen = 0;
    let mut versions_seen = BTreeSet::new();
    let t0 = Instant::now();
    for _ in 0..kills {
        let mut c = child("child_write_forever", tmp.path())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("{e}"));
        let mut lines = BufReader::new(c.stdout.take().unwrap_or_else(|| panic!("stdout")));
        // wait until the child is writing, then kill it a random moment later
        let mut line = String::new();
        while announced(&line).is_none() {
            line.clear();
            if lines.read_line(&mut line).unwrap_or(0) == 0 {
                panic!("writer exited before writing");
            }
        }
        std::thread::sleep(Duration::from_micros(rng.random_range(0..30_000)));
        c.kill().unwrap_or_else(|e| panic!("kill: {e}"));
        let _ = c.wait();
        // every version the child announced (it announces before writing)
        let mut rest = String::new();
        let _ = std::io::Read::read_to_string(&mut lines, &mut rest);
        for l in line.lines().chain(rest.lines()) {
            if let Some(n) = announced(l) {
                max_attempted = max_attempted.max(n);
            }
        }
        if files_under(tmp.path())
            .iter()
            .any(|f| f.to_string_lossy().contains(".tmp-"))
        {
            stray_seen += 1;
        }
        // current.json parses and is exactly one of the versions written, never older than before
        let folder = store.device_dir(CRASH_ID);
        if !folder.join(store::CURRENT).exists() {
            assert_eq!(last_version, 0, "current.json vanished");
            continue;
        }
        let (mut p, _) = store.current(CRASH_ID).unwrap_or_else(|e| panic!("{e}"));
        let v = version_of(&p);
        p.change = None;
        assert_eq!(
            p,
            profile(CRASH_ID, v, true),
            "current.json is version {v} exactly"
        );
        assert!(
            v >= last_version && v <= max_attempted,
            "{v} not in {last_version}..={max_attempted}"
        );
        last_version = v;
        versions_seen.insert(v);
    }
    let elapsed = t0.elapsed();
    // every history file is a complete version too, each at most once
    let history = store.history(CRASH_ID).unwrap_or_else(|e| panic!("{e}"));
    let mut hv = BTreeMap::new();
    for h in &history {
        let mut p = read_document(h).unwrap_or_else(|e| panic!("{}: {e}", h.display()));
        let v = version_of(&p);
        p.change = None;
        assert_eq!(p, profile(CRASH_ID, v, true));
        *hv.entry(v).or_insert(0) += 1;
    }
    assert!(hv.values().all(|&n| n == 1), "duplicated history entries");
    println!(
        "{kills} SIGKILLs in {:.1} s: {} versions written, {} distinct current versions seen, {} history files, temp files left by a kill {} times",
        elapsed.as_secs_f64(),
        max_attempted,
        versions_seen.len(),
        history.len(),
        stray_seen
    );
    assert!(
        versions_seen.len() >= 20,
        "the children got profiles written between kills"
    );
    assert!(
        stray_seen > 0,
        "no kill landed inside a write: the test did not test anything"
    );
    // the next writer cleans up what the killed ones left
    commit(&store, &profile(CRASH_ID, max_attempted + 1, true)).unwrap_or_else(|e| panic!("{e}"));
    let stray: Vec<PathBuf> = files_under(tmp.path())
        .into_iter()
        .filter(|f| f.to_string_lossy().contains(".tmp-"))
        .collect();
    assert!(stray.is_empty(), "{stray:?}");
}

// ---------------------------------------------------------------------------------------------------
// acceptance 5: the exports in the real tools

/// The Python interpreter with the tools, and whether they are all importable.
fn python_with_tools() -> Option<String> {
    let candidates = [
        std::env::var("CUBECAL_PYTHON").ok(),
        Some("/usr/bin/python3".to_string()),
        Some("python3".to_string()),
    ];
    candidates.into_iter().flatten().find(|py| {
        Command::new(py)
            .args(["-c", "import cv2, mrcal, camera_calibration_parsers, yaml"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    })
}

fn tools_required() -> bool {
    std::env::var("CUBECAL_REQUIRE_TOOLS").is_ok_and(|v| v == "1")
}

/// Strongly distorted lenses: ~300 px of distortion in the corners of a 1280×960 image.
fn distorted_cameras() -> Vec<(&'static str, Camera)> {
    vec![
        (
            "brown5",
            Camera::pinhole([1280, 960], 800.0, 803.5, 641.25, 478.75).with_distortion(
                DistortionModel::Brown5,
                &[-0.3, 0.1, 0.0015, -0.0012, -0.01],
            ),
        ),
        (
            "brown5_no_k3",
            Camera::pinhole([1280, 960], 800.0, 803.5, 641.25, 478.75)
                .with_distortion(DistortionModel::Brown5, &[-0.3, 0.1, 0.0015, -0.0012, 0.0]),
        ),
        (
            "brown8",
            Camera::pinhole([1280, 960], 760.0, 758.0, 636.0, 483.0).with_distortion(
                DistortionModel::Brown8,
                &[0.4, 0.05, 0.0008, -0.0011, 0.002, 0.65, 0.1, 0.004],
            ),
        ),
        (
            "pinhole",
            Camera::pinhole([640, 480], 500.0, 500.0, 319.5, 239.5),
        ),
    ]
}

/// Points whose images cover the whole frame, corners and edges included: a grid of pixels
/// unprojected with cubecal's model and pushed to depths 0.3–5 m.
fn points_covering_the_image(cam: &Camera) -> Vec<Vector3<f64>> {
    let [w, h] = cam.image_size.map(f64::from);
    let mut pts = Vec::new();
    let steps = 16;
    for i in 0..=steps {
        for j in 0..=steps {
            let (u, v) = (
                -0.5 + w * i as f64 / steps as f64,
                -0.5 + h * j as f64 / steps as f64,
            );
            let ray = cam
                .unproject(u, v)
                .unwrap_or_else(|e| panic!("unproject ({u}, {v}): {e}"));
            let depth = 300.0 + 4700.0 * ((i * 7 + j * 3) % 11) as f64 / 10.0;
            pts.push(ray / ray.z * depth);
        }
    }
    pts
}

/// The Python interpreter with the tools, or `None` after saying why the test is skipped (a failure
/// under `CUBECAL_REQUIRE_TOOLS=1`).
fn python_or_skip(test: &str) -> Option<String> {
    let python = python_with_tools();
    if python.is_none() {
        let reason = "python3 with cv2, mrcal, camera_calibration_parsers and yaml not found (run deploy/install-test-tools.sh)";
        assert!(!tools_required(), "CUBECAL_REQUIRE_TOOLS=1 but {reason}");
        eprintln!("SKIPPED {test}: {reason}");
    }
    python
}

/// Run `tests/exports/project.py` on `dir` and parse what it prints.
fn project_with_tools(python: &str, dir: &Path, name: &str) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/exports/project.py");
    let out = Command::new(python)
        .arg(&script)
        .arg(dir)
        .output()
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(
        out.status.success(),
        "{name}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// A tool's pixels, `None` where it could not project the point.
fn pixels(v: &serde_json::Value, tool: &str) -> Vec<Option<[f64; 2]>> {
    serde_json::from_value(v[tool].clone()).unwrap_or_else(|e| panic!("{tool}: {e}"))
}

/// Largest distance between our pixels and a tool's over the points it projected, and how many.
fn max_distance(ours: &[[f64; 2]], theirs: &[Option<[f64; 2]>]) -> (f64, usize) {
    assert_eq!(theirs.len(), ours.len());
    ours.iter()
        .zip(theirs)
        .filter_map(|(a, b)| b.map(|b| (a[0] - b[0]).hypot(a[1] - b[1])))
        .fold((0.0, 0), |(m, n), d| (m.max(d), n + 1))
}

/// The `points.json` the export peers (`tests/exports/project.py`) project.
fn points_json(pts: &[Vector3<f64>]) -> String {
    serde_json::json!({ "points": pts.iter().map(|x| [x.x, x.y, x.z]).collect::<Vec<_>>() })
        .to_string()
}

/// `cam`'s own projection of every point, as the peers' scripts print theirs.
fn project_all(cam: &Camera, pts: &[Vector3<f64>]) -> Vec<[f64; 2]> {
    pts.iter()
        .map(|x| {
            let uv = cam.project_cam(x).unwrap_or_else(|e| panic!("{e}"));
            [uv.x, uv.y]
        })
        .collect()
}

#[test]
fn exports_load_in_opencv_ros_and_mrcal_and_project_like_cubecal() {
    let Some(python) = python_or_skip("exports test") else {
        return;
    };
    for (name, cam) in distorted_cameras() {
        let tmp = tempdir();
        let mut p = profile("usb:046d:0825:EXPORT", 0, true);
        p.calibration = report(&cam, 0.1);
        let pts = points_covering_the_image(&cam);
        let ours = project_all(&cam, &pts);
        // the points reach the image corners, and the lens bends them there
        let corner = ours[0];
        assert!(
            (corner[0] + 0.5).abs() < 1e-6 && (corner[1] + 0.5).abs() < 1e-6,
            "{corner:?}"
        );
        let write = |file: &str, text: String| {
            std::fs::write(tmp.path().join(file), text).unwrap_or_else(|e| panic!("{e}"))
        };
        write("points.json", points_json(&pts));
        write(
            "opencv.yaml",
            export::opencv_yaml(&p).unwrap_or_else(|e| panic!("{e}")),
        );
        write(
            "ros.yaml",
            export::ros_camera_info_yaml(&p).unwrap_or_else(|e| panic!("{e}")),
        );
        write(
            "model.cameramodel",
            export::mrcal_cameramodel(&p).unwrap_or_else(|e| panic!("{e}")),
        );
        // Kalibr's radtan has no k3: the lenses with one are refused (kalibr_refuses_…)
        let kalibr = export::kalibr_camchain_yaml(&p);
        assert_eq!(
            kalibr.is_ok(),
            matches!(name, "pinhole" | "brown5_no_k3"),
            "{name}: {kalibr:?}"
        );
        let mut tools = vec!["opencv", "ros", "mrcal"];
        if let Ok(text) = kalibr {
            write("kalibr.yaml", text);
            tools.push("kalibr");
        }
        let v = project_with_tools(&python, tmp.path(), name);
        for tool in tools {
            let (max_err, n) = max_distance(&ours, &pixels(&v, tool));
            assert_eq!(n, ours.len(), "{name} via {tool}: every point projected");
            let max_shift = pts
                .iter()
                .zip(&ours)
                .map(|(x, uv)| {
                    let pin = [
                        cam.fx() * x.x / x.z + cam.cx(),
                        cam.fy() * x.y / x.z + cam.cy(),
                    ];
                    (pin[0] - uv[0]).hypot(pin[1] - uv[1])
                })
                .fold(0.0, f64::max);
            println!(
                "{name} via {tool}: {} points, max |cubecal − {tool}| = {max_err:.3e} px (distortion up to {max_shift:.0} px)",
                ours.len()
            );
            assert!(max_err < 1e-6, "{name} via {tool}: {max_err} px");
        }
        let loaded = &v["loaded"];
        assert!(loaded["opencv"]["fisheye_model"].is_null(), "{name}");
        assert_eq!(loaded["opencv"]["size"], serde_json::json!(cam.image_size));
        assert_eq!(loaded["ros"]["size"], serde_json::json!(cam.image_size));
        assert_eq!(loaded["mrcal"]["size"], serde_json::json!(cam.image_size));
        let expected_model = match cam.model {
            DistortionModel::Brown8 => "rational_polynomial",
            _ => "plumb_bob",
        };
        assert_eq!(loaded["ros"]["model"], expected_model);
        assert_eq!(loaded["ros"]["name"], "usb_046d_0825_EXPORT");
    }
}

/// Rays from the axis to 100° off it, at 24 azimuths and depths of 0.3–5 m, whose images cubecal puts
/// inside the frame: the fisheye's field to where it passes 90° (a point behind the camera's plane).
fn fisheye_points(cam: &Camera) -> Vec<Vector3<f64>> {
    let thetas_deg = [
        0.0, 0.5, 2.0, 5.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 85.0, 88.0, 89.0, 89.9,
        90.5, 92.0, 95.0, 98.0, 100.0,
    ];
    let [w, h] = cam.image_size.map(f64::from);
    let mut pts = Vec::new();
    for (i, &t) in thetas_deg.iter().enumerate() {
        for j in 0..24 {
            let (th, ph) = (
                f64::to_radians(t),
                f64::to_radians(15.0 * j as f64 + 7.0 * i as f64),
            );
            let depth = 300.0 + 4700.0 * ((i * 7 + j * 3) % 11) as f64 / 10.0;
            let p = Vector3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()) * depth;
            let uv = cam
                .project_cam(&p)
                .unwrap_or_else(|e| panic!("{t}° {ph}: {e}"));
            if (-0.5..w - 0.5).contains(&uv.x) && (-0.5..h - 0.5).contains(&uv.y) {
                pts.push(p);
            }
            if t == 0.0 {
                break;
            }
        }
    }
    pts
}

/// Angle off the optical axis, degrees.
fn off_axis_deg(p: &Vector3<f64>) -> f64 {
    p.x.hypot(p.y).atan2(p.z).to_degrees()
}

#[test]
fn kb4_exports_load_in_cv2_fisheye_ros_and_kalibr_and_project_like_cubecal() {
    let Some(python) = python_or_skip("kb4 exports test") else {
        return;
    };
    let [k1, k2, ..] = kb4_camera().distortion_coefficients()[..] else {
        panic!("kb4 has 4 coefficients");
    };
    let cahvore_exact = kb4_camera().with_distortion(DistortionModel::Kb4, &[k1, k2, 0.0, 0.0]);
    for (name, cam) in [("kb4", kb4_camera()), ("kb4 k3=k4=0", cahvore_exact)] {
        let tmp = tempdir();
        let mut p = profile("usb:2bdf:0280:FISHEYE", 0, true);
        p.calibration = report(&cam, 0.1);
        let pts = fisheye_points(&cam);
        let ours = project_all(&cam, &pts);
        let in_front = pts.iter().filter(|x| x.z > 0.0).count();
        let widest = pts.iter().map(off_axis_deg).fold(0.0, f64::max);
        let widest_in_front = pts
            .iter()
            .filter(|x| x.z > 0.0)
            .map(off_axis_deg)
            .fold(0.0, f64::max);
        assert!(
            widest > 99.9 && widest_in_front > 89.8,
            "{widest} {widest_in_front}"
        );
        assert!(
            pts.len() - in_front >= 40,
            "points past 90°: {}",
            pts.len() - in_front
        );
        let write = |file: &str, text: String| {
            std::fs::write(tmp.path().join(file), text).unwrap_or_else(|e| panic!("{e}"))
        };
        write("points.json", points_json(&pts));
        for (file, text) in [
            ("opencv.yaml", export::opencv_yaml(&p)),
            ("ros.yaml", export::ros_camera_info_yaml(&p)),
            ("kalibr.yaml", export::kalibr_camchain_yaml(&p)),
        ] {
            write(file, text.unwrap_or_else(|e| panic!("{name} {file}: {e}")));
        }
        // mrcal: refused (naming the model), unless k3 = k4 = 0 makes CAHVORE an exact equivalent
        match (name, export::mrcal_cameramodel(&p)) {
            ("kb4", Err(e)) => {
                let msg = e.to_string();
                assert!(
                    msg.starts_with("cannot export to mrcal: the kb4 lens (Kannala–Brandt"),
                    "{msg}"
                );
                println!("{name} via mrcal: refused: {msg}");
            }
            ("kb4 k3=k4=0", Ok(text)) => write("model.cameramodel", text),
            (_, other) => panic!("{name}: mrcal export {other:?}"),
        }
        let v = project_with_tools(&python, tmp.path(), name);

        // cv::fisheye (OpenCV's file and ROS's), and Kalibr's equidistant, in front of the camera
        for tool in ["opencv", "ros", "kalibr"] {
            let (max_err, n) = max_distance(&ours, &pixels(&v, tool));
            println!(
                "{name} via {tool}: {n} points with z > 0 (up to {widest_in_front:.1}° off the axis), max |cubecal − {tool}| = {max_err:.3e} px"
            );
            assert_eq!(n, in_front, "{name} via {tool}: every point with z > 0");
            assert!(max_err < 1e-6, "{name} via {tool}: {max_err} px");
        }
        // past 90°: the file's K and D through cv::fisheye's formula on the angle give our pixels …
        let (max_err, n) = max_distance(&ours, &pixels(&v, "opencv_theta"));
        println!(
            "{name} via cv::fisheye's formula on θ with the loaded K, D: {n} points up to {widest:.1}°, max |Δ| = {max_err:.3e} px"
        );
        assert!(n == pts.len() && max_err < 1e-6, "{name}: {max_err} px");
        // … while cv2.fisheye.projectPoints, which divides by z first, puts a point behind the
        // camera's plane where the point reflected through the centre belongs
        let reflected: Vec<[f64; 2]> = pts
            .iter()
            .map(|x| match cam.project_cam(&-x) {
                Ok(uv) if x.z <= 0.0 => [uv.x, uv.y],
                _ => [f64::NAN, f64::NAN],
            })
            .collect();
        let (max_err, n) = max_distance(&reflected, &pixels(&v, "opencv_behind"));
        println!(
            "{name}: cv2.fisheye.projectPoints of the {n} points past 90° = cubecal's projection of −X within {max_err:.3e} px (their reflection)"
        );
        assert!(n == pts.len() - in_front && max_err < 1e-6, "{max_err}");
        if name == "kb4 k3=k4=0" {
            let (max_err, n) = max_distance(&ours, &pixels(&v, "mrcal"));
            println!(
                "{name} via mrcal (LENSMODEL_CAHVORE_linearity=0.00): {n} points up to {widest:.1}°, max |Δ| = {max_err:.3e} px"
            );
            assert!(
                n == pts.len() && max_err < 1e-6,
                "{name} via mrcal: {max_err} px"
            );
            assert_eq!(
                v["loaded"]["mrcal"]["lensmodel"],
                "LENSMODEL_CAHVORE_linearity=0.00"
            );
        } else {
            assert!(v["mrcal"].is_null());
        }

        // what each tool read: exactly our numbers
        let coeffs = cam.distortion_coefficients();
        let k = serde_json::json!([
            [cam.fx(), 0.0, cam.cx()],
            [0.0, cam.fy(), cam.cy()],
            [0.0, 0.0, 1.0]
        ]);
        let loaded = &v["loaded"];
        assert_eq!(loaded["opencv"]["fisheye_model"], 1);
        assert_eq!(loaded["opencv"]["K"], k);
        assert_eq!(loaded["opencv"]["D"], serde_json::json!(coeffs));
        assert_eq!(loaded["opencv"]["size"], serde_json::json!(cam.image_size));
        assert_eq!(loaded["ros"]["model"], "equidistant");
        assert_eq!(loaded["ros"]["K"], k);
        assert_eq!(loaded["ros"]["D"], serde_json::json!(coeffs));
        assert_eq!(loaded["ros"]["size"], serde_json::json!(cam.image_size));
        assert_eq!(
            loaded["ros"]["P"],
            serde_json::json!([
                cam.fx(),
                0.0,
                cam.cx(),
                0.0,
                0.0,
                cam.fy(),
                cam.cy(),
                0.0,
                0.0,
                0.0,
                1.0,
                0.0
            ])
        );
        let cam0 = &loaded["kalibr"]["cam0"];
        assert_eq!(
            loaded["kalibr"]
                .as_object()
                .map(|o| o.keys().cloned().collect::<Vec<_>>()),
            Some(vec!["cam0".to_string()])
        );
        assert_eq!(cam0["camera_model"], "pinhole");
        assert_eq!(
            cam0["intrinsics"],
            serde_json::json!([cam.fx(), cam.fy(), cam.cx(), cam.cy()])
        );
        assert_eq!(cam0["distortion_model"], "equidistant");
        assert_eq!(cam0["distortion_coeffs"], serde_json::json!(coeffs));
        assert_eq!(cam0["resolution"], serde_json::json!(cam.image_size));
        assert!(cam0.get("T_cam_imu").is_none(), "{cam0}");
        assert_eq!(cam0["rostopic"], "/cam0/image_raw");
    }
}

#[test]
fn mrcal_and_kalibr_refuse_what_they_cannot_express_exactly() {
    let export_of = |cam: &Camera, f: fn(&Profile) -> Result<String, export::ExportError>| {
        let mut p = profile("cam", 0, true);
        p.calibration = report(cam, 0.1);
        f(&p)
    };
    let refused = |r: Result<String, export::ExportError>| match r {
        Err(e @ export::ExportError::Unsupported { .. }) => e.to_string(),
        other => panic!("expected a refusal, got {other:?}"),
    };
    // mrcal has no lens model with kb4's θ⁷, θ⁹ terms
    let msg = refused(export_of(&kb4_camera(), export::mrcal_cameramodel));
    assert!(
        msg.contains("kb4") && msg.contains("Kannala–Brandt") && msg.contains("k3 = 5.20e-4"),
        "{msg}"
    );
    // Kalibr's radtan is k1, k2, p1, p2: a k3 (or brown8's rational terms) is refused, naming them
    let cams = distorted_cameras();
    let by_name = |n: &str| {
        cams.iter()
            .find(|(name, _)| *name == n)
            .map(|(_, c)| c.clone())
            .unwrap_or_else(|| panic!("{n}"))
    };
    let msg = refused(export_of(&by_name("brown5"), export::kalibr_camchain_yaml));
    assert!(
        msg.starts_with(
            "cannot export to Kalibr: the brown5 lens has k3 = -1.00e-2; Kalibr's radtan"
        ),
        "{msg}"
    );
    let msg = refused(export_of(&by_name("brown8"), export::kalibr_camchain_yaml));
    assert!(
        msg.contains("the brown8 lens has k3 = 2.00e-3, k4 = 6.50e-1, k5 = 1.00e-1, k6 = 4.00e-3"),
        "{msg}"
    );
    // … and what it can express exactly is written: brown8 with k3..k6 = 0 is radtan, pinhole none
    let radtan8 = by_name("brown8").with_distortion(
        DistortionModel::Brown8,
        &[0.4, 0.05, 0.0008, -0.0011, 0.0, 0.0, 0.0, 0.0],
    );
    let text = export_of(&radtan8, export::kalibr_camchain_yaml).unwrap_or_else(|e| panic!("{e}"));
    assert!(
        text.contains(
            "  distortion_model: radtan\n  distortion_coeffs: [0.4, 0.05, 0.0008, -0.0011]\n"
        ),
        "{text}"
    );
    let text = export_of(&by_name("pinhole"), export::kalibr_camchain_yaml)
        .unwrap_or_else(|e| panic!("{e}"));
    assert!(
        text.contains("  intrinsics: [500.0, 500.0, 319.5, 239.5]\n  distortion_model: none\n  distortion_coeffs: []\n  resolution: [640, 480]\n"),
        "{text}"
    );
}

#[test]
fn colmap_line_shifts_the_principal_point_and_picks_the_model() {
    let cameras = distorted_cameras()
        .into_iter()
        .chain([("kb4", kb4_camera())]);
    for (name, cam) in cameras {
        let mut p = profile("cam", 0, true);
        p.calibration = report(&cam, 0.1);
        let text = export::colmap_cameras_txt(&p).unwrap_or_else(|e| panic!("{e}"));
        let line = text
            .lines()
            .find(|l| !l.starts_with('#'))
            .unwrap_or_else(|| panic!("{text}"));
        let f: Vec<&str> = line.split(' ').collect();
        let model = match name {
            "brown5" => "FULL_OPENCV", // k3 ≠ 0 does not fit COLMAP's OPENCV
            "brown5_no_k3" => "OPENCV",
            "brown8" => "FULL_OPENCV",
            "kb4" => "OPENCV_FISHEYE", // fx, fy, cx, cy, k1, k2, k3, k4
            _ => "PINHOLE",
        };
        assert_eq!(
            f[..4],
            [
                "1",
                model,
                &cam.image_size[0].to_string(),
                &cam.image_size[1].to_string()
            ]
        );
        let nums: Vec<f64> = f[4..]
            .iter()
            .map(|s| s.parse().unwrap_or(f64::NAN))
            .collect();
        assert_eq!(
            nums[..4],
            [cam.fx(), cam.fy(), cam.cx() + 0.5, cam.cy() + 0.5]
        );
        let mut coeffs = cam.distortion_coefficients();
        coeffs.resize(
            match model {
                "PINHOLE" => 0,
                "OPENCV" | "OPENCV_FISHEYE" => 4,
                _ => 8,
            },
            0.0,
        );
        assert_eq!(nums[4..], coeffs[..], "{name}: {line}");
    }
}

#[test]
fn exports_refuse_skew() {
    let mut p = profile("cam", 0, true);
    p.calibration.camera_matrix[0][1] = 0.25;
    for f in export::Format::ALL {
        assert!(
            matches!(f.render(&p), Err(export::ExportError::Unsupported { .. })),
            "{f:?}"
        );
    }
}

// ---------------------------------------------------------------------------------------------------
// acceptance 6 on a real full file system: a 256 KiB tmpfs in a private mount namespace

#[test]
fn child_disk_full() {
    let Some(dir) = is_child("child_disk_full") else {
        return;
    };
    let store = Store::open(&dir.join("store")).unwrap_or_else(|e| panic!("{e}"));
    let id = "usb:1234:5678:TMPFS";
    let v1 = commit(&store, &profile(id, 1, true)).unwrap_or_else(|e| panic!("{e}"));
    let v1_bytes = read(&v1.current);
    // fill the file system
    let mut filler = std::fs::File::create(dir.join("filler")).unwrap_or_else(|e| panic!("{e}"));
    let chunk = vec![0u8; 4096];
    let full = loop {
        if let Err(e) = filler.write_all(&chunk).and_then(|()| filler.sync_all()) {
            break e;
        }
    };
    assert_eq!(full.kind(), std::io::ErrorKind::StorageFull, "{full}");
    match commit(&store, &profile(id, 2, true)) {
        Err(e @ ProfileError::Write { .. }) => {
            let kind = std::error::Error::source(&e)
                .and_then(|s| s.downcast_ref::<std::io::Error>())
                .map(|e| e.kind());
            assert_eq!(kind, Some(std::io::ErrorKind::StorageFull), "{e}");
            println!("DISK-FULL-OK {e}");
        }
        other => panic!("expected a write error on a full disk, got {other:?}"),
    }
    assert_eq!(read(&v1.current), v1_bytes, "previous profile intact");
    // room again: the next commit works
    drop(filler);
    std::fs::remove_file(dir.join("filler")).unwrap_or_else(|e| panic!("{e}"));
    commit(&store, &profile(id, 2, true)).unwrap_or_else(|e| panic!("{e}"));
}

#[test]
fn a_full_tmpfs_gives_a_typed_error_and_keeps_the_previous_profile() {
    let tmp = tempdir();
    let exe = std::env::current_exe().unwrap_or_else(|e| panic!("{e}"));
    // user + mount namespace: mount a tiny tmpfs over the temp dir, visible to the child only
    let out = Command::new("unshare")
        .args(["-rm", "sh", "-c"])
        .arg(r#"mount -t tmpfs -o size=256k tmpfs "$1" || exit 97; shift; exec "$@""#)
        .arg("sh")
        .arg(tmp.path())
        .arg(&exe)
        .args([
            "child_disk_full",
            "--exact",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD_VAR, "child_disk_full")
        .env(DIR_VAR, tmp.path())
        .output();
    // 97: mount refused; 1 with no output: unshare itself refused (no user namespaces)
    let setup_failed = |o: &std::process::Output| {
        o.status.code() == Some(97) || (o.status.code() == Some(1) && o.stdout.is_empty())
    };
    let out = match out {
        Ok(o) if !setup_failed(&o) => o,
        Ok(o) => {
            eprintln!(
                "SKIPPED real disk-full test: cannot mount a tmpfs in a user namespace here ({})",
                String::from_utf8_lossy(&o.stderr).trim()
            );
            return;
        }
        Err(e) => {
            eprintln!("SKIPPED real disk-full test: unshare not available ({e})");
            return;
        }
    };
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && stdout.contains("DISK-FULL-OK"),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    println!(
        "{}",
        stdout
            .lines()
            .find(|l| l.contains("DISK-FULL-OK"))
            .unwrap_or("")
    );
}

// ---------------------------------------------------------------------------------------------------
// the command line

fn cubecal(args: &[&str], store: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(args)
        .arg("--store")
        .arg(store)
        .output()
        .unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn cli_show_export_diff_rollback_and_their_exit_codes() {
    let tmp = tempdir();
    let root = tmp.path().join("store");
    let store = Store::open(&root).unwrap_or_else(|e| panic!("{e}"));
    let id = "usb:046d:0825:CLI";
    let v1 = commit(&store, &profile(id, 1, true)).unwrap_or_else(|e| panic!("{e}"));
    let v1_bytes = read(&v1.current);
    commit(&store, &profile(id, 5000, true)).unwrap_or_else(|e| panic!("{e}"));
    let text = |o: &std::process::Output| String::from_utf8_lossy(&o.stdout).into_owned();

    let out = cubecal(&["profile", "show", id], &root);
    assert_eq!(out.status.code(), Some(0));
    assert!(text(&out).contains("fx 1005.0000"), "{}", text(&out));
    assert!(text(&out).contains("JUMP"), "{}", text(&out));
    let out = cubecal(&["--json", "profile", "show", &folder_name(id)], &root);
    assert_eq!(
        out.stdout,
        read(&v1.current),
        "--json prints the stored document"
    );

    let out = cubecal(&["profile", "export", id, "--format", "ros"], &root);
    assert_eq!(out.status.code(), Some(0));
    let (p, _) = store.current(id).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        text(&out),
        export::ros_camera_info_yaml(&p).unwrap_or_else(|e| panic!("{e}"))
    );
    let out = cubecal(&["profile", "export", id, "--format", "png"], &root);
    assert_eq!(out.status.code(), Some(2), "unknown format: usage");
    // a lens a format cannot express is refused whole (exit 3), saying what to do
    let out = cubecal(&["profile", "export", id, "--format", "kalibr"], &root);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{err}");
    assert!(
        err.starts_with("error: cannot export to Kalibr: the brown5 lens has k3 = -1.00e-2;")
            && err.ends_with("(for Kalibr: --model brown5 --fix k3)\n"),
        "{err}"
    );

    let history = store.history(id).unwrap_or_else(|e| panic!("{e}"));
    let old = history[0].to_string_lossy().into_owned();
    let out = cubecal(&["--json", "profile", "diff", &old, id], &root);
    assert_eq!(out.status.code(), Some(0));
    let change: cubecal::profile::Change =
        serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}"));
    assert!(change.jump && (change.params[0].delta - 4.999).abs() < 1e-9);

    let out = cubecal(&["profile", "rollback", id], &root);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(read(&v1.current), v1_bytes);
    let out = cubecal(&["profile", "rollback", id], &root);
    assert_eq!(out.status.code(), Some(3), "nothing left to roll back");
    let out = cubecal(&["profile", "show", "usb:no:such:camera"], &root);
    assert_eq!(out.status.code(), Some(3));

    // a camera another writer holds is exit 4
    let _lock = store.lock(id).unwrap_or_else(|e| panic!("{e}"));
    let out = cubecal(&["profile", "rollback", id], &root);
    assert_eq!(
        out.status.code(),
        Some(4),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
