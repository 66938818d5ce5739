//! ChArUco faces (issue 33): the dictionaries against OpenCV's bit for bit, and detection on renders
//! of the 3-face ChArUco cube (`fixtures/rigs/charuco_cube.toml`) against the exact ground truth and
//! OpenCV's ChArUco detector (`tests/peers/charuco_opencv.py`) on the same frames.
//!
//! The OpenCV parts need python3 with cv2.aruco (`deploy/install-test-tools.sh`); without it they
//! are skipped with a message, unless `CUBECAL_REQUIRE_TOOLS=1` makes that a failure.
#![allow(clippy::print_stderr)]

#[path = "support/aruco.rs"]
mod aruco;

use std::path::{Path, PathBuf};
use std::process::Command;

use aruco::{python_with_aruco, run_peer};
use cubecal::detect::score::{EvalSet, score};
use cubecal::detect::{CornerFinder, detect};
use cubecal::render::{ground_truth, render};
use cubecal::rig::Rig;
use cubecal::rig::charuco::{DICTIONARY_NAMES, Dictionary, opencv_corner_id};

fn rig_text() -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/rigs/charuco_cube.toml");
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Every marker of the 12 dictionaries, drawn by OpenCV one pixel per cell, against our table.
#[test]
fn dictionaries_are_opencvs_bit_for_bit() {
    let Some(py) = python_with_aruco() else {
        return;
    };
    let script = r#"
import cv2, sys
a = cv2.aruco
draw = getattr(a, "generateImageMarker", None) or a.drawMarker
for name in sys.argv[1:]:
    d = a.getPredefinedDictionary(getattr(a, name))
    n = d.markerSize
    codes = []
    for i in range(d.bytesList.shape[0]):
        img = draw(d, i, n + 2)
        code = 0
        for r in range(n):
            for c in range(n):
                code = (code << 1) | int(img[r + 1, c + 1] > 127)
        codes.append(format(code, "x"))
    print(name, d.maxCorrectionBits, " ".join(codes))
"#;
    let out = Command::new(&py)
        .arg("-c")
        .arg(script)
        .args(DICTIONARY_NAMES)
        .output()
        .unwrap_or_else(|e| panic!("{py}: {e}"));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    let mut checked = 0;
    for line in text.lines() {
        let mut parts = line.split_whitespace();
        let name = parts.next().unwrap_or_default();
        let dict = Dictionary::from_name(name).unwrap_or_else(|| panic!("{name}"));
        let max: u32 = parts
            .next()
            .and_then(|v| v.parse().ok())
            .unwrap_or(u32::MAX);
        assert_eq!(dict.max_correction_bits(), max, "{name}: maxCorrectionBits");
        let codes: Vec<u64> = parts
            .map(|c| u64::from_str_radix(c, 16).unwrap_or(u64::MAX))
            .collect();
        assert_eq!(codes.len(), dict.count, "{name}: markers");
        assert_eq!(
            dict.codes(),
            &codes[..],
            "{name}: bits differ from OpenCV's"
        );
        checked += 1;
    }
    assert_eq!(checked, 12);
}

struct Frame {
    png: PathBuf,
    truth: cubecal::render::GroundTruth,
}

fn render_frames(rig: &Rig, dir: &Path, set: EvalSet, n: usize) -> Vec<Frame> {
    let (camera, settings) = (set.camera(), set.settings());
    set.poses(rig, n)
        .iter()
        .enumerate()
        .map(|(k, pose)| {
            let img =
                render(rig, &camera, pose, &settings, k as u64).unwrap_or_else(|e| panic!("{e}"));
            let png = dir.join(format!("{}_{k}.png", set.name()));
            img.save(&png)
                .unwrap_or_else(|e| panic!("{}: {e}", png.display()));
            Frame {
                png,
                truth: ground_truth(rig, &camera, pose, &settings, k as u64),
            }
        })
        .collect()
}

/// Acceptance 1 (the part this test can show cheaply): on renders of the ChArUco cube, no corner is
/// labelled wrong, and the corners are closer to the truth than OpenCV's CharucoDetector's on the
/// same frames. Corner counts of both are printed (`--nocapture`).
#[test]
fn charuco_cube_renders_label_right_and_beat_opencv_rms() {
    let (rig, _) =
        Rig::from_toml_str(&rig_text(), "charuco_cube.toml").unwrap_or_else(|e| panic!("{e}"));
    let tmp = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let frames = render_frames(&rig, tmp.path(), EvalSet::Realistic, 2);
    let mut finder = CornerFinder::new().unwrap_or_else(|e| panic!("{e}"));
    let (mut ours_sq, mut ours_n) = (0.0, 0usize);
    let mut ours_per_frame = Vec::new();
    for f in &frames {
        let img = image::open(&f.png)
            .unwrap_or_else(|e| panic!("{e}"))
            .to_luma8();
        let det = detect(&mut finder, &img, &rig).unwrap_or_else(|e| panic!("{e}"));
        let scores = score(&rig, &f.truth, &det);
        let wrong: usize = scores.iter().map(|s| s.mislabelled).sum();
        assert_eq!(wrong, 0, "{}: wrong labels", f.png.display());
        let corners: usize = scores.iter().map(|s| s.corners).sum();
        assert!(corners >= 40, "{}: only {corners} corners", f.png.display());
        ours_per_frame.push(corners);
        for s in &scores {
            ours_sq += s.errors.iter().map(|e| e * e).sum::<f64>();
            ours_n += s.errors.len();
        }
    }
    let ours_rms = (ours_sq / ours_n as f64).sqrt();
    eprintln!("cubecal: corners per frame {ours_per_frame:?}, RMS {ours_rms:.4} px");
    let Some(py) = python_with_aruco() else {
        return;
    };
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
    let spec = tmp.path().join("boards.json");
    std::fs::write(&spec, serde_json::json!({"boards": boards}).to_string())
        .unwrap_or_else(|e| panic!("{e}"));
    let mut args = vec![spec.into_os_string()];
    args.extend(frames.iter().map(|f| f.png.clone().into_os_string()));
    let cv: serde_json::Value =
        serde_json::from_slice(&run_peer(&py, &args)).unwrap_or_else(|e| panic!("{e}"));
    let (mut cv_sq, mut cv_n) = (0.0, 0usize);
    let mut cv_per_frame = Vec::new();
    for (f, im) in frames
        .iter()
        .zip(cv["images"].as_array().into_iter().flatten())
    {
        let mut count = 0;
        for (fi, face) in rig.faces.iter().enumerate() {
            for c in im["boards"][&face.name].as_array().into_iter().flatten() {
                let id = c[0].as_u64().unwrap_or(u64::MAX) as usize;
                let (x, y) = (
                    c[1].as_f64().unwrap_or(f64::NAN),
                    c[2].as_f64().unwrap_or(f64::NAN),
                );
                let truth = f
                    .truth
                    .corners
                    .iter()
                    .find(|t| {
                        t.face_index == fi
                            && opencv_corner_id(face.cols, face.rows, t.row, t.col) == id
                    })
                    .and_then(|t| t.uv)
                    .unwrap_or_else(|| panic!("OpenCV corner {id} of {} has no truth", face.name));
                let e2 = (truth[0] - x).powi(2) + (truth[1] - y).powi(2);
                cv_sq += e2;
                cv_n += 1;
                count += 1;
            }
        }
        cv_per_frame.push(count);
    }
    let cv_rms = (cv_sq / cv_n.max(1) as f64).sqrt();
    eprintln!(
        "OpenCV {}: corners per frame {cv_per_frame:?}, RMS {cv_rms:.4} px",
        cv["cv2"]
    );
    assert!(
        ours_rms <= cv_rms,
        "RMS {ours_rms:.4} px above OpenCV's {cv_rms:.4} px"
    );
}

/// Acceptance 4 (part): a board of the same dictionary with other ids, and the cube's boards in
/// another dictionary, label nothing.
#[test]
fn boards_with_other_ids_or_dictionary_label_nothing() {
    let text = rig_text();
    let (rig, _) = Rig::from_toml_str(&text, "charuco_cube.toml").unwrap_or_else(|e| panic!("{e}"));
    for (what, other) in [
        (
            "other ids",
            text.replace("first_id = 0 ", "first_id = 150 ")
                .replace("first_id = 32 ", "first_id = 182 ")
                .replace("first_id = 64 ", "first_id = 214 "),
        ),
        (
            "another dictionary",
            text.replace("DICT_5X5_250", "DICT_6X6_250"),
        ),
    ] {
        let (shown, _) = Rig::from_toml_str(&other, "other.toml").unwrap_or_else(|e| panic!("{e}"));
        let set = EvalSet::Realistic;
        let pose = set.poses(&shown, 1)[0];
        let img = render(&shown, &set.camera(), &pose, &set.settings(), 0)
            .unwrap_or_else(|e| panic!("{e}"));
        let mut finder = CornerFinder::new().unwrap_or_else(|e| panic!("{e}"));
        let det = detect(&mut finder, &img, &rig).unwrap_or_else(|e| panic!("{e}"));
        let labelled: usize = det.faces.iter().map(|f| f.corners.len()).sum();
        assert_eq!(labelled, 0, "{what}: {labelled} corners labelled");
    }
}

/// Corner (0, 0) of a face SVG of `rig print`, in page mm: the top-right corner of square (0, 0)
/// when it is black, else the top-left corner of square (0, 1).
fn svg_corner00(svg: &str) -> Option<[f64; 2]> {
    let attr = |tag: &str, name: &str| -> Option<f64> {
        let at = tag.find(&format!(" {name}=\""))? + name.len() + 3;
        tag[at..].split('"').next()?.parse().ok()
    };
    for (col, right) in [("0", true), ("1", false)] {
        let key = format!("data-row=\"0\" data-col=\"{col}\"");
        if let Some(at) = svg.find(&key) {
            let tag = &svg[at..at + svg[at..].find("/>")?];
            let (x, y, w) = (attr(tag, "x")?, attr(tag, "y")?, attr(tag, "width")?);
            return Some([if right { x + w } else { x }, y]);
        }
    }
    None
}

/// cubecal's labels of one face in an image: OpenCV corner id → position.
fn cubecal_labels(rig: &Rig, face: usize, png: &Path) -> Vec<(usize, [f64; 2])> {
    let img = image::open(png)
        .unwrap_or_else(|e| panic!("{}: {e}", png.display()))
        .to_luma8();
    let mut finder = CornerFinder::new().unwrap_or_else(|e| panic!("{e}"));
    let det = detect(&mut finder, &img, rig).unwrap_or_else(|e| panic!("{e}"));
    let f = &rig.faces[face];
    let mut out: Vec<(usize, [f64; 2])> = det
        .faces
        .iter()
        .filter(|d| d.face == face)
        .flat_map(|d| d.corners.iter())
        .map(|c| {
            (
                opencv_corner_id(f.cols, f.rows, c.row, c.col),
                [c.uv.x, c.uv.y],
            )
        })
        .collect();
    let others: usize = det
        .faces
        .iter()
        .filter(|d| d.face != face)
        .map(|d| d.corners.len())
        .sum();
    assert_eq!(others, 0, "{}: corners of other faces", png.display());
    out.sort_by_key(|c| c.0);
    out
}

/// Acceptance 2: a face printed by `rig print` (its SVG drawn at 32 px a square) decodes in OpenCV
/// to the face's marker ids and every corner id, at the places cubecal labels them; and a board
/// OpenCV draws itself (generateImage, `board.draw` on 4.6) decodes in cubecal, every corner id at
/// its exact place. Three layouts: 8 × 8 squares (DICT_5X5_250), 10 × 10 (DICT_6X6_1000, ids from
/// 50), 18 × 9 (DICT_4X4_250).
#[test]
fn printed_boards_decode_in_opencv_and_opencv_boards_in_cubecal() {
    let Some(py) = python_with_aruco() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/rigs");
    // The least corners cubecal labels on OpenCV's drawing: all. (OpenCV 4.6 draws the 10 × 10
    // board's markers up to a pixel from their place; with markers 0.75 of a square the fit's
    // window, ±3 px at 32 px a square, then took in a marker's edge at 9 of the 81 corners, until
    // the fit was restarted a pixel away: `charuco::fit_corner`.)
    for (file, face, least_on_opencvs) in [
        ("charuco_cube.toml", 0, 49),
        ("pycamset_ccube.toml", 1, 81),
        ("pycalib_charuco_wide.toml", 0, 136),
    ] {
        let (rig, _) = Rig::load(&dir.join(file)).unwrap_or_else(|e| panic!("{e}"));
        let f = &rig.faces[face];
        let Some(ch) = &f.charuco else {
            panic!("{file}: face {face} is no ChArUco face")
        };
        let n_corners = f.cols * f.rows;
        let spec = tmp.path().join(format!("{file}.json"));
        let board = serde_json::json!({"name": f.name, "dictionary": ch.dictionary.name(),
            "squares": [f.cols + 1, f.rows + 1], "square": f.square_mm,
            "marker": ch.marker_mm, "ids": ch.ids});
        std::fs::write(&spec, serde_json::json!({"boards": [board]}).to_string())
            .unwrap_or_else(|e| panic!("{e}"));

        // cubecal's print, read by OpenCV.
        let svg = tmp.path().join(format!("{file}.svg"));
        std::fs::write(&svg, cubecal::rig::svg::face_svg(&rig, f))
            .unwrap_or_else(|e| panic!("{e}"));
        let printed = tmp.path().join(format!("{file}.printed.png"));
        let px_per_mm = format!("{}", 32.0 / f.square_mm);
        run_peer(
            &py,
            &[
                "--rasterise".as_ref(),
                svg.as_os_str(),
                printed.as_os_str(),
                px_per_mm.as_ref(),
            ],
        );
        let cv: serde_json::Value =
            serde_json::from_slice(&run_peer(&py, &[spec.as_os_str(), printed.as_os_str()]))
                .unwrap_or_else(|e| panic!("{e}"));
        let im = &cv["images"][0];
        let mut ids: Vec<u32> = im["markers"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|m| m[0].as_u64().unwrap_or(u64::MAX) as u32)
            .collect();
        ids.sort_unstable();
        let mut want = ch.ids.clone();
        want.sort_unstable();
        assert_eq!(ids, want, "{file}: OpenCV's marker ids on the printed face");
        let cv_corners: Vec<(usize, [f64; 2])> = im["boards"][&f.name]
            .as_array()
            .into_iter()
            .flatten()
            .map(|c| {
                (
                    c[0].as_u64().unwrap_or(u64::MAX) as usize,
                    [
                        c[1].as_f64().unwrap_or(f64::NAN),
                        c[2].as_f64().unwrap_or(f64::NAN),
                    ],
                )
            })
            .collect();
        let ours = cubecal_labels(&rig, face, &printed);
        assert_eq!(cv_corners.len(), n_corners, "{file}: OpenCV's corners");
        assert_eq!(ours.len(), n_corners, "{file}: cubecal's corners");
        // Where the SVG puts each corner: square (0, 0) or (0, 1) (whichever is black) fixes
        // corner (0, 0); rows run up the page.
        let ppm = 32.0 / f.square_mm;
        let corner00 = svg_corner00(&std::fs::read_to_string(&svg).unwrap_or_default())
            .unwrap_or_else(|| panic!("{file}: no square (0, 0) or (0, 1) in the SVG"));
        let truth = |id: usize| -> [f64; 2] {
            let (c, r) = (id % f.cols, f.rows - 1 - id / f.cols);
            [
                (corner00[0] + c as f64 * f.square_mm) * ppm - 0.5,
                (corner00[1] - r as f64 * f.square_mm) * ppm - 0.5,
            ]
        };
        let dist =
            |a: [f64; 2], b: [f64; 2]| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
        let ours_worst = ours
            .iter()
            .map(|(id, uv)| dist(*uv, truth(*id)))
            .fold(0.0, f64::max);
        let cv_worst = cv_corners
            .iter()
            .map(|(id, uv)| dist(*uv, truth(*id)))
            .fold(0.0, f64::max);
        eprintln!(
            "{file}: printed face read by OpenCV {}: {} markers, {n_corners} corners, at most {cv_worst:.3} px from their place (cubecal {ours_worst:.3} px)",
            cv["cv2"],
            ids.len()
        );
        assert!(
            cv_worst < 0.25 * 32.0,
            "{file}: an OpenCV corner {cv_worst:.3} px from the place of its id"
        );
        assert!(
            ours_worst < 0.1,
            "{file}: a cubecal corner {ours_worst:.3} px off"
        );

        // OpenCV's drawing, read by cubecal: corner (x, y) lies between pixels, at
        // margin + (x + 1)·32 − 0.5 (pixel centres are integers).
        let drawn = tmp.path().join(format!("{file}.opencv.png"));
        run_peer(
            &py,
            &[
                "--generate".as_ref(),
                spec.as_os_str(),
                f.name.as_ref(),
                drawn.as_os_str(),
                "32".as_ref(),
                "32".as_ref(),
            ],
        );
        let ours = cubecal_labels(&rig, face, &drawn);
        assert!(
            ours.len() >= least_on_opencvs,
            "{file}: cubecal labels {} of {n_corners} corners on OpenCV's board",
            ours.len()
        );
        let mut worst: f64 = 0.0;
        for (id, uv) in &ours {
            let (x, y) = ((id % f.cols) as f64, (id / f.cols) as f64);
            let want = [32.0 + (x + 1.0) * 32.0 - 0.5, 32.0 + (y + 1.0) * 32.0 - 0.5];
            worst = worst.max(((want[0] - uv[0]).powi(2) + (want[1] - uv[1]).powi(2)).sqrt());
        }
        eprintln!(
            "{file}: OpenCV's board read by cubecal: {} of {n_corners} corners, at most {worst:.3} px from their place",
            ours.len()
        );
        assert!(worst < 0.1, "{file}: a corner {worst:.3} px off");
    }
}

/// A face of `rig` drawn frontally in OpenCV's layout, 56 px a square with a 56 px margin, each
/// marker with `flips(marker index)` of its data bits inverted (the ids on the face unchanged).
fn draw_face_with_flips(
    face: &cubecal::rig::Face,
    mut flips: impl FnMut(usize, usize) -> Vec<usize>,
) -> image::GrayImage {
    let ch = face
        .charuco
        .as_ref()
        .unwrap_or_else(|| panic!("no ChArUco face"));
    let (sx, sy) = (face.cols + 1, face.rows + 1);
    let ppm = 56.0 / face.square_mm;
    let sq = 56usize;
    let mut img = image::GrayImage::from_pixel(
        (sx * sq + 2 * sq) as u32,
        (sy * sq + 2 * sq) as u32,
        image::Luma([235]),
    );
    let n = ch.dictionary.bits;
    let cell = (ch.marker_mm * ppm / (n + 2) as f64).round() as usize;
    let mut k = 0;
    for y in 0..sy {
        for x in 0..sx {
            let (x0, y0) = (sq + x * sq, sq + y * sq);
            if (x + y) % 2 == 0 {
                for yy in y0..y0 + sq {
                    for xx in x0..x0 + sq {
                        img.put_pixel(xx as u32, yy as u32, image::Luma([20]));
                    }
                }
                continue;
            }
            let mut code = ch.dictionary.codes()[ch.ids[k] as usize];
            for b in flips(k, n * n) {
                code ^= 1 << b;
            }
            k += 1;
            let m0 = (
                x0 + (sq - cell * (n + 2)) / 2,
                y0 + (sq - cell * (n + 2)) / 2,
            );
            for r in 0..n + 2 {
                for c in 0..n + 2 {
                    let inner = r >= 1 && c >= 1 && r <= n && c <= n;
                    let light = inner && (code >> (n * n - 1 - ((r - 1) * n + (c - 1)))) & 1 == 1;
                    let v = if light { 235 } else { 20 };
                    for yy in 0..cell {
                        for xx in 0..cell {
                            img.put_pixel(
                                (m0.0 + c * cell + xx) as u32,
                                (m0.1 + r * cell + yy) as u32,
                                image::Luma([v]),
                            );
                        }
                    }
                }
            }
        }
    }
    image::imageops::blur(&img, 1.0)
}

/// Acceptance 4 (random bit flips): markers with 0–6 of their data bits flipped at random (seeded),
/// 20 boards: no corner is ever labelled with another id; markers within the dictionary's
/// correction still label their corners. The unflipped board labels every corner (the drawing is
/// right).
#[test]
fn random_bit_flips_never_label_wrong() {
    use rand::{Rng, SeedableRng};
    let (rig, _) =
        Rig::from_toml_str(&rig_text(), "charuco_cube.toml").unwrap_or_else(|e| panic!("{e}"));
    let face = &rig.faces[0];
    let mut finder = CornerFinder::new().unwrap_or_else(|e| panic!("{e}"));
    let truth = |id: usize| -> [f64; 2] {
        let (x, y) = ((id % face.cols) as f64, (id / face.cols) as f64);
        [56.0 + (x + 1.0) * 56.0 - 0.5, 56.0 + (y + 1.0) * 56.0 - 0.5]
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(33);
    let (mut labelled, mut wrong) = (0, 0);
    for board in 0..21 {
        let img = draw_face_with_flips(face, |_, bits| {
            if board == 0 {
                return Vec::new();
            }
            let k = rng.random_range(0..=6usize);
            (0..k).map(|_| rng.random_range(0..bits)).collect()
        });
        let det = detect(&mut finder, &img, &rig).unwrap_or_else(|e| panic!("{e}"));
        let mut n = 0;
        for f in &det.faces {
            for c in &f.corners {
                n += 1;
                let id = opencv_corner_id(face.cols, face.rows, c.row, c.col);
                let t = truth(id);
                if f.face != 0 || ((c.uv.x - t[0]).powi(2) + (c.uv.y - t[1]).powi(2)).sqrt() > 28.0
                {
                    wrong += 1;
                }
            }
        }
        if board == 0 {
            assert_eq!(n, face.cols * face.rows, "the unflipped board");
        }
        labelled += n;
    }
    eprintln!("bit flips: {labelled} corners labelled on 21 boards, {wrong} wrong");
    assert_eq!(wrong, 0, "corners labelled with another id");
    assert!(
        labelled > face.cols * face.rows,
        "nothing labelled on the flipped boards"
    );
}

/// Markers read where their decoded neighbours predict them (`charuco` step 4): marker 10 of a
/// face, its black border cut into four by two light lines (its outline no region of its own), is
/// read where the markers around it put it and its four corners labelled; with the bits of an id
/// on no face in its place, none of the four is labelled, and no corner is labelled wrong.
#[test]
fn cut_marker_read_where_its_neighbours_put_it_with_its_own_bits_only() {
    let (rig, _) =
        Rig::from_toml_str(&rig_text(), "charuco_cube.toml").unwrap_or_else(|e| panic!("{e}"));
    let face = &rig.faces[0];
    let ch = face
        .charuco
        .as_ref()
        .unwrap_or_else(|| panic!("no ChArUco face"));
    let n = ch.dictionary.bits;
    let stranger = 200u32;
    assert!(
        rig.faces.iter().all(|f| f
            .charuco
            .as_ref()
            .is_none_or(|c| !c.ids.contains(&stranger))),
        "id {stranger} is on a face"
    );
    // Marker 10 sits in square (5, 2); 56 px squares after a 56 px margin, 6 px cells from 7 px in.
    let (k, id) = (10usize, ch.ids[10]);
    let (cell, x0, y0) = (6u32, 56 + 5 * 56 + 7, 56 + 2 * 56 + 7);
    let cut = |img: &mut image::GrayImage| {
        // 2 px light lines on the cells' boundaries 3 | 4, clear of the cells' middle halves.
        for t in 0..7 * cell + 6 {
            for d in 0..2 {
                let (a, b) = (x0 + 3 * cell - 1 + d, y0 + t - 3);
                img.put_pixel(a, b, image::Luma([235]));
                // The same line transposed about the marker's corner (x0, y0).
                img.put_pixel(x0 + t - 3, y0 + 3 * cell - 1 + d, image::Luma([235]));
            }
        }
    };
    let truth = |cid: usize| -> [f64; 2] {
        let (x, y) = ((cid % face.cols) as f64, (cid / face.cols) as f64);
        [56.0 + (x + 1.0) * 56.0 - 0.5, 56.0 + (y + 1.0) * 56.0 - 0.5]
    };
    let beside = [11usize, 12, 18, 19];
    let mut finder = CornerFinder::new().unwrap_or_else(|e| panic!("{e}"));
    for replaced in [false, true] {
        let own = ch.dictionary.codes()[id as usize];
        let swap = ch.dictionary.codes()[stranger as usize];
        let mut img = draw_face_with_flips(face, |m, bits| {
            if replaced && m == k {
                (0..bits).filter(|b| ((own ^ swap) >> b) & 1 == 1).collect()
            } else {
                Vec::new()
            }
        });
        cut(&mut img);
        let regions = cubecal::detect::charuco::find_markers(&img, &[ch.dictionary]);
        assert!(
            regions.iter().all(|m| m.id != id && m.id != stranger),
            "the cut marker decoded from its region: the test shows nothing"
        );
        let det = detect(&mut finder, &img, &rig).unwrap_or_else(|e| panic!("{e}"));
        let mut labelled = Vec::new();
        for f in &det.faces {
            for c in &f.corners {
                let cid = opencv_corner_id(face.cols, face.rows, c.row, c.col);
                let t = truth(cid);
                let off = ((c.uv.x - t[0]).powi(2) + (c.uv.y - t[1]).powi(2)).sqrt();
                assert!(
                    f.face == 0 && off < 1.0,
                    "corner {cid} of face {} labelled {off:.1} px from its place",
                    f.face
                );
                labelled.push(cid);
            }
        }
        let n_beside = beside.iter().filter(|c| labelled.contains(c)).count();
        eprintln!(
            "cut marker{}: {} corners labelled, {n_beside} of the 4 beside it ({n}×{n} bits)",
            if replaced {
                " with another id's bits"
            } else {
                ""
            },
            labelled.len()
        );
        if replaced {
            assert_eq!(
                n_beside, 0,
                "a corner beside the other id's marker labelled"
            );
            assert_eq!(labelled.len(), face.cols * face.rows - 4);
        } else {
            assert_eq!(labelled.len(), face.cols * face.rows, "every corner");
        }
    }
}
