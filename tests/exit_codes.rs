//! The README's "Exit codes by command" table, row by row: every row is run here (one example of that
//! failure) and must give the documented code, and every row here must be in the README, so that the
//! documentation and the binary cannot drift apart.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::Path;
use std::process::{Command, Output};

fn cubecal(args: &[String]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .expect("run cubecal")
}

/// The rows of the README table under `### Exit codes by command`: (command, failure, code).
fn readme_rows() -> Vec<(String, String, u8)> {
    let readme =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap();
    let start = readme
        .find("### Exit codes by command")
        .expect("README has '### Exit codes by command'");
    readme[start..]
        .lines()
        .skip_while(|l| !l.starts_with('|'))
        .take_while(|l| l.starts_with('|'))
        .skip(2) // header and rule
        .map(|l| {
            let cells: Vec<&str> = l.trim_matches('|').split('|').map(str::trim).collect();
            assert_eq!(cells.len(), 3, "row {l}");
            (
                cells[0].trim_matches('`').to_string(),
                cells[1].to_string(),
                cells[2].parse().unwrap_or_else(|_| panic!("code in {l}")),
            )
        })
        .collect()
}

struct Case {
    command: &'static str,
    failure: &'static str,
    code: u8,
    /// Example arguments; `{tmp}` is replaced by a fresh temporary directory.
    args: &'static [&'static str],
}

const RIG: &str = "fixtures/rigs/cube_outside.toml";
const FRAME: &str = "fixtures/render/cube_outside/frame_000.png";
const OBS: &str = "fixtures/observations/cube_synthetic.json";

const CASES: &[Case] = &[
    Case {
        command: "any",
        failure: "unknown subcommand or option, missing or malformed argument, contradictory options",
        code: 2,
        args: &["solve", OBS, "--estimate-skew", "--fix", "skew"],
    },
    Case {
        command: "solve",
        failure: "observations missing, malformed or inconsistent (a point outside `image_size`, an absurd value, a duplicate view name)",
        code: 3,
        args: &["solve", "{tmp}/missing.json"],
    },
    Case {
        command: "solve",
        failure: "no convergence, or parameters not determined by the data",
        code: 5,
        args: &["solve", OBS, "--max-iterations", "1"],
    },
    Case {
        command: "render",
        failure: "rig missing or invalid, invalid camera or effect values",
        code: 3,
        args: &["render", "{tmp}/missing.toml", "--out", "{tmp}/frames"],
    },
    Case {
        command: "render",
        failure: "output directory cannot be created or written",
        code: 7,
        args: &[
            "render",
            RIG,
            "--out",
            "/proc/cubecal-cannot-write",
            "--width",
            "64",
            "--height",
            "48",
        ],
    },
    Case {
        command: "detect",
        failure: "rig or image missing, unreadable or undecodable",
        code: 3,
        args: &["detect", "--rig", RIG, "{tmp}/missing.png"],
    },
    Case {
        command: "detect",
        failure: "overlay cannot be written",
        code: 7,
        args: &[
            "detect",
            "--rig",
            RIG,
            FRAME,
            "--overlay",
            "{tmp}/no/such/dir/o.png",
        ],
    },
    Case {
        command: "detect",
        failure: "two images would write the same overlay, an overlay name that is not `.png`",
        code: 2,
        args: &["detect", "--rig", RIG, FRAME, "--overlay", "{tmp}/o.jpg"],
    },
    Case {
        command: "rig print",
        failure: "rig missing or invalid",
        code: 3,
        args: &["rig", "print", "{tmp}/missing.toml", "--out", "{tmp}/svg"],
    },
    Case {
        command: "rig print",
        failure: "SVG cannot be written",
        code: 7,
        args: &["rig", "print", RIG, "--out", "/proc/cubecal-cannot-write"],
    },
    Case {
        command: "record",
        failure: "`--format` not one cubecal converts, `--frames`/`--width`/`--height`/`--fps` 0 (checked before the device is opened)",
        code: 2,
        args: &[
            "record",
            "--device",
            "{tmp}/video9",
            "--out",
            "{tmp}/s",
            "--format",
            "FOO",
        ],
    },
    Case {
        command: "record",
        failure: "device missing, busy, not permitted, or failing mid-run",
        code: 4,
        args: &["record", "--device", "{tmp}/video9", "--out", "{tmp}/s"],
    },
    Case {
        command: "turntable",
        failure: "`--port` missing for `grbl` or `zaber`",
        code: 2,
        args: &["turntable", "status", "--protocol", "grbl"],
    },
    Case {
        command: "turntable",
        failure: "angle not finite or beyond ±3600°",
        code: 3,
        args: &[
            "turntable",
            "move",
            "--protocol",
            "grbl",
            "--port",
            "{tmp}/tty",
            "5000",
        ],
    },
    Case {
        command: "turntable",
        failure: "port missing, busy or not permitted; the turntable does not answer or reports a fault",
        code: 4,
        args: &[
            "turntable",
            "status",
            "--protocol",
            "grbl",
            "--port",
            "{tmp}/tty",
        ],
    },
    Case {
        command: "calibrate",
        failure: "config missing or invalid, run directory already exists",
        code: 3,
        args: &["calibrate", "--config", "{tmp}/missing.toml"],
    },
    Case {
        command: "calibrate",
        failure: "`--images`: not one photo usable (missing, empty, not an image)",
        code: 3,
        args: &[
            "calibrate",
            "--rig",
            RIG,
            "--images",
            "{tmp}/missing.jpg",
            "--out",
            "{tmp}/run",
        ],
    },
    Case {
        command: "calibrate",
        failure: "camera or turntable missing, busy or failing",
        code: 4,
        args: &[
            "calibrate",
            "--device",
            "{tmp}/video9",
            "--out",
            "{tmp}/run",
        ],
    },
    Case {
        command: "calibrate",
        failure: "run directory cannot be created or written",
        code: 7,
        args: &[
            "calibrate",
            "--synthetic",
            "--out",
            "/proc/cubecal-cannot-write",
        ],
    },
    Case {
        command: "calibrate",
        failure: "photos without `--rig` or `--board`, a `--set` without `=` (checked before anything is opened)",
        code: 2,
        args: &["calibrate", "--images", FRAME, "--out", "{tmp}/run"],
    },
    Case {
        command: "profile",
        failure: "store directory missing, no profile for the camera, a profile file unreadable, malformed or of a newer format, a lens the export format cannot express exactly",
        code: 3,
        args: &["profile", "list", "--store", "{tmp}/no-such-store"],
    },
];

#[test]
fn every_documented_failure_gives_its_code() {
    let readme = readme_rows();
    let ours: Vec<(String, String, u8)> = CASES
        .iter()
        .map(|c| (c.command.to_string(), c.failure.to_string(), c.code))
        .chain(std::iter::once((
            "devices".to_string(),
            "no V4L2 capture device found".to_string(),
            4,
        )))
        .collect();
    for row in &readme {
        assert!(
            ours.contains(row),
            "README row {row:?} is not exercised here"
        );
    }
    for row in &ours {
        assert!(readme.contains(row), "{row:?} is not in the README table");
    }
    for case in CASES {
        let dir = tempfile::tempdir().unwrap();
        let tmp = dir.path().to_str().unwrap();
        let args: Vec<String> = case.args.iter().map(|a| a.replace("{tmp}", tmp)).collect();
        for json in [false, true] {
            let mut args = args.clone();
            if json {
                args.push("--json".into());
            }
            let out = cubecal(&args);
            let err = String::from_utf8_lossy(&out.stderr);
            assert_eq!(
                out.status.code(),
                Some(i32::from(case.code)),
                "{} / {}: {args:?}\n{err}",
                case.command,
                case.failure
            );
            assert!(!err.contains("panicked"), "{err}");
            if json {
                let v: serde_json::Value = serde_json::from_slice(&out.stdout)
                    .unwrap_or_else(|e| panic!("{args:?}: stdout is not JSON ({e})"));
                // An error is an error object; a calibration that did not converge is still printed
                // as the report, saying so.
                let reported =
                    v["exit_code"] == case.code || (case.code == 5 && v["converged"] == false);
                assert!(reported, "{args:?}: {v}");
            }
        }
    }
}

/// `devices` exits 4 exactly when it lists no device (this machine may or may not have one).
#[test]
fn devices_exits_4_when_there_is_none() {
    let out = cubecal(&["devices".to_string()]);
    let listed = !out.stdout.is_empty();
    let code = out.status.code();
    if listed {
        assert_eq!(code, Some(0));
    } else {
        assert_eq!(code, Some(4));
        assert!(
            String::from_utf8_lossy(&out.stderr).contains("no V4L2 capture devices found"),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

/// The general table lists exactly the codes of `cubecal::exit`.
#[test]
fn readme_general_table_matches_the_constants() {
    let readme =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap();
    let start = readme.find("## Exit codes").unwrap();
    let codes: Vec<u8> = readme[start..]
        .lines()
        .skip_while(|l| !l.starts_with('|'))
        .take_while(|l| l.starts_with('|'))
        .skip(2)
        .map(|l| {
            l.trim_matches('|')
                .split('|')
                .next()
                .unwrap()
                .trim()
                .parse()
                .unwrap()
        })
        .collect();
    use cubecal::exit::*;
    assert_eq!(
        codes,
        [
            SUCCESS,
            INTERNAL,
            USAGE,
            BAD_INPUT,
            DEVICE,
            CALIBRATION_FAILED,
            QA_REJECTED,
            IO,
            INTERRUPTED
        ]
    );
}
