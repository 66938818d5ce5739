//! Rig descriptions: the shipped fixtures, face geometry, validation errors naming their key, warnings,
//! and printable SVG boards checked by parsing their geometry back.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::{Path, PathBuf};

use cubecal::rig::svg::{PageLayout, SCALE_BAR_MM, face_svg};
use cubecal::rig::{BoardRegion, Rig, RigError, RigWarning, SquareColour};
use nalgebra::Vector3;
use proptest::prelude::*;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures/rigs")
        .join(name)
}

fn load(name: &str) -> (Rig, Vec<RigWarning>) {
    let path = fixture(name);
    Rig::load(&path).unwrap_or_else(|e| panic!("fixture {} must load: {e}", path.display()))
}

const GOOD: &str = r#"
name = "two-walls"
units = "mm"
[[faces]]
name = "left"
cols = 5
rows = 4
square_mm = 20.0
origin = [0, 40, 40]
col_dir = [0, 1, 0]
row_dir = [0, 0, 1]
[[faces]]
name = "right"
cols = 6
rows = 3
square_mm = 20.0
origin = [160, 0, 40]
col_dir = [-1, 0, 0]
row_dir = [0, 0, 1]
"#;

fn parse(text: &str) -> Result<(Rig, Vec<RigWarning>), RigError> {
    Rig::from_toml_str(text, "rig.toml")
}

fn err(text: &str) -> RigError {
    match parse(text) {
        Ok(_) => panic!("expected an error for:\n{text}"),
        Err(e) => e,
    }
}

/// The full message with its causes, as the CLI prints it.
fn chain(e: &RigError) -> String {
    let mut s = e.to_string();
    let mut cur: Option<&dyn std::error::Error> = std::error::Error::source(e);
    while let Some(c) = cur {
        s.push_str(" | ");
        s.push_str(&c.to_string());
        cur = c.source();
    }
    s
}

#[test]
fn shipped_rigs_load_with_the_documented_grids() {
    let (cube, warnings) = load("cube_outside.toml");
    assert!(warnings.is_empty(), "{warnings:?}");
    let grids: Vec<_> = cube
        .faces
        .iter()
        .map(|f| (f.name.as_str(), f.cols, f.rows))
        .collect();
    assert_eq!(grids, [("top", 9, 8), ("side-x", 8, 7), ("side-y", 7, 6)]);
    let body = cube.body.unwrap();
    let centre = (body.min + body.max) / 2.0;
    for f in &cube.faces {
        // Normals point out of the cube; boards lie on its surface, inside the face.
        assert!(f.normal().dot(&(f.origin - centre)) > 0.0, "{}", f.name);
        for p in f.outline() {
            assert!(
                (0..3).all(|k| p[k] >= -1e-9 && p[k] <= 200.0 + 1e-9),
                "{} {p:?}",
                f.name
            );
        }
    }
    assert_eq!(cube.up, Vector3::z());

    let (inside, warnings) = load("inside_corner.toml");
    assert!(warnings.is_empty(), "{warnings:?}");
    assert_eq!(inside.faces.len(), 3);
    for f in &inside.faces {
        // Normals point into the room (the positive octant).
        assert!(f.normal().iter().all(|&c| c >= -1e-12) && (f.normal().sum() - 1.0).abs() < 1e-12);
    }

    let (flat, warnings) = load("opencv_board_9x6.toml");
    assert!(warnings.is_empty(), "{warnings:?}");
    let f = &flat.faces[0];
    assert_eq!((f.cols, f.rows, f.square_mm), (9, 6, 30.0));
    assert_eq!(flat.n_corners(), 54);
}

#[test]
fn corner_positions_normals_and_square_colours() {
    let (rig, _) = parse(GOOD).unwrap();
    let right = &rig.faces[1];
    assert_eq!(
        rig.corner_xyz(1, 2, 3),
        Some(Vector3::new(100.0, 0.0, 80.0))
    );
    assert_eq!(right.corner_xyz(2, 3), Vector3::new(100.0, 0.0, 80.0));
    assert_eq!(rig.corner_xyz(1, 3, 0), None, "row out of range");
    assert_eq!(rig.corner_xyz(2, 0, 0), None, "no such face");
    assert_eq!(right.normal(), Vector3::new(0.0, 1.0, 0.0));
    assert_eq!(rig.faces[0].normal(), Vector3::new(1.0, 0.0, 0.0));
    assert_eq!(right.square_colour(0, 0), SquareColour::Black);
    assert_eq!(right.square_colour(0, 1), SquareColour::White);
    assert_eq!(right.square_colour(3, 6), SquareColour::White);
    // Face coordinates and regions: square (i, j) spans a ∈ [(j−1)s, js], b ∈ [(i−1)s, is].
    assert_eq!(
        right.region_at(-10.0, -10.0),
        BoardRegion::Square { i: 0, j: 0 }
    );
    assert_eq!(
        right.region_at(110.0, 50.0),
        BoardRegion::Square { i: 3, j: 6 }
    );
    assert_eq!(right.region_at(-25.0, 0.0), BoardRegion::Margin);
    assert_eq!(right.region_at(-45.0, 0.0), BoardRegion::Outside);
    // Outline includes the default margin of one square.
    let ([a0, a1], [b0, b1]) = right.board_extent();
    assert_eq!((a0, a1, b0, b1), (-40.0, 140.0, -40.0, 80.0));
    assert_eq!(rig.corners().count(), rig.n_corners());
    assert_eq!(rig.n_corners(), 20 + 18);
}

proptest! {
    /// `is_point_symmetric` is exactly "the pattern maps onto itself under a 180° rotation".
    #[test]
    fn point_symmetry_matches_the_pattern(cols in 2usize..12, rows in 2usize..12, white in any::<bool>()) {
        let text = format!(
            "name = \"p\"\nunits = \"mm\"\n[[faces]]\nname = \"f\"\ncols = {cols}\nrows = {rows}\nsquare_mm = 10.0\n\
             origin = [0, 0, 0]\ncol_dir = [1, 0, 0]\nrow_dir = [0, 1, 0]\nfirst_square = \"{}\"\n",
            if white { "white" } else { "black" }
        );
        let (rig, warnings) = parse(&text).unwrap();
        let f = &rig.faces[0];
        let symmetric = (0..=rows).all(|i| (0..=cols).all(|j| f.square_colour(i, j) == f.square_colour(rows - i, cols - j)));
        prop_assert_eq!(f.is_point_symmetric(), symmetric);
        let warned = warnings.iter().any(|w| matches!(w, RigWarning::SymmetricGrid { .. }));
        prop_assert_eq!(warned, symmetric);
    }
}

#[test]
fn warnings_are_returned_as_data() {
    let text = GOOD.replace("cols = 6\nrows = 3", "cols = 5\nrows = 3");
    let (_, warnings) = parse(&text).unwrap();
    assert_eq!(
        warnings,
        [RigWarning::SymmetricGrid {
            face: "right".into(),
            cols: 5,
            rows: 3
        }]
    );
    let text = GOOD.replace("cols = 6\nrows = 3", "cols = 4\nrows = 5");
    let (_, warnings) = parse(&text).unwrap();
    assert_eq!(
        warnings,
        [RigWarning::SameGridSize {
            a: "left".into(),
            b: "right".into()
        }]
    );
    assert!(warnings[0].to_string().contains("cannot tell them apart"));
}

#[test]
fn missing_keys_are_named_by_path() {
    let e = err(&GOOD.replacen("cols = 6\n", "", 1));
    assert!(
        matches!(&e, RigError::Missing { key, .. } if key == "faces[1].cols"),
        "{e:?}"
    );
    assert_eq!(e.to_string(), "rig.toml: faces[1].cols: missing");
    let e = err(&GOOD.replacen("square_mm = 20.0\n", "", 1));
    assert_eq!(e.to_string(), "rig.toml: faces[0].square_mm: missing");
    let e = err(&GOOD.replacen("row_dir = [0, 0, 1]\n", "", 1));
    assert_eq!(e.to_string(), "rig.toml: faces[0].row_dir: missing");
    let e = err(&GOOD.replacen("name = \"two-walls\"\n", "", 1));
    assert_eq!(e.to_string(), "rig.toml: name: missing");
    let e = err("name = \"x\"\nunits = \"mm\"\n");
    assert_eq!(e.to_string(), "rig.toml: faces: missing");
    assert_eq!(e.exit_code(), cubecal::exit::BAD_INPUT);
}

#[test]
fn bad_values_are_named_by_path() {
    let e = err(&GOOD.replacen("cols = 6", "cols = -3", 1));
    assert_eq!(
        e.to_string(),
        "rig.toml: faces[1].cols: expected a positive integer ≥ 2, got -3"
    );
    let e = err(&GOOD.replacen("square_mm = 20.0", "square_mm = -5", 1));
    assert_eq!(
        e.to_string(),
        "rig.toml: faces[0].square_mm: expected a positive length in mm, got -5"
    );
    let e = err(&GOOD.replacen("square_mm = 20.0", "square_mm = 0", 1));
    assert!(
        e.to_string()
            .starts_with("rig.toml: faces[0].square_mm: expected a positive length")
    );
    let e = err(&GOOD.replacen("rows = 3", "rows = 3\nmargin_mm = -1", 1));
    assert!(
        e.to_string()
            .starts_with("rig.toml: faces[1].margin_mm: expected a length ≥ 0"),
        "{e}"
    );
    let e = err(&GOOD.replacen("units = \"mm\"", "units = \"inch\"", 1));
    assert_eq!(
        e.to_string(),
        "rig.toml: units: expected \"mm\", got \"inch\""
    );
    let e = err(&GOOD.replacen("name = \"right\"", "name = \"left\"", 1));
    assert!(
        e.to_string()
            .starts_with("rig.toml: faces[1].name: expected a name unique"),
        "{e}"
    );
    assert_eq!(e.exit_code(), cubecal::exit::BAD_INPUT);
}

#[test]
fn open_sides_are_read_and_bad_ones_named_by_path() {
    let (rig, _) = parse(&GOOD.replacen(
        "rows = 3",
        "rows = 3\nopen_sides = [\"last_row\", \"first_col\"]",
        1,
    ))
    .unwrap();
    assert!(rig.faces[0].open_sides.is_empty());
    assert_eq!(
        rig.faces[1].open_sides,
        [
            cubecal::rig::FaceSide::LastRow,
            cubecal::rig::FaceSide::FirstCol
        ]
    );
    let e = err(&GOOD.replacen("rows = 3", "rows = 3\nopen_sides = [\"top\"]", 1));
    assert_eq!(
        e.to_string(),
        "rig.toml: faces[1].open_sides[0]: expected one of \"first_row\", \"last_row\", \"first_col\", \"last_col\", got \"top\""
    );
    let e = err(&GOOD.replacen(
        "rows = 3",
        "rows = 3\nopen_sides = [\"last_col\", \"last_col\"]",
        1,
    ));
    assert!(
        e.to_string()
            .starts_with("rig.toml: faces[1].open_sides[1]: expected each side at most once"),
        "{e}"
    );
    let e = err(&GOOD.replacen(
        "rows = 3",
        "rows = 3\nopen_sides = [\"first_row\", \"last_row\"]",
        1,
    ));
    assert!(
        e.to_string().starts_with(
            "rig.toml: faces[1].open_sides[1]: expected at most one of two opposite sides"
        ),
        "{e}"
    );
    let e = err(&GOOD.replacen("rows = 3", "rows = 3\nopen_sides = \"last_row\"", 1));
    assert!(chain(&e).contains("open_sides"), "{}", chain(&e));
    assert_eq!(e.exit_code(), cubecal::exit::BAD_INPUT);
    // The shipped photo rig: one wall runs off every view on its side away from the fold.
    // No "same grid size" warning: a face with open sides is not told apart by its size.
    let (bailus, warnings) = load("bailus_inside_corner.toml");
    assert!(warnings.is_empty(), "{warnings:?}");
    let open: Vec<_> = bailus.faces.iter().map(|f| f.open_sides.clone()).collect();
    assert_eq!(open, [vec![], vec![cubecal::rig::FaceSide::LastRow]]);
}

#[test]
fn non_orthonormal_axes_are_rejected_with_the_face() {
    let e = err(&GOOD.replacen("row_dir = [0, 0, 1]", "row_dir = [0, 0.5, 0.866]", 1));
    assert!(
        matches!(&e, RigError::NotOrthonormal { index: 0, .. }),
        "{e:?}"
    );
    assert!(
        e.to_string()
            .starts_with("rig.toml: faces[0] (left): col_dir and row_dir must be orthonormal"),
        "{e}"
    );
    assert!(e.to_string().contains("col_dir · row_dir = 0.5"), "{e}");
    let e = err(&GOOD.replacen("col_dir = [-1, 0, 0]", "col_dir = [-2, 0, 0]", 1));
    assert!(
        e.to_string().contains("faces[1] (right)") && e.to_string().contains("|col_dir| = 2"),
        "{e}"
    );
    // Hand-typed unit vectors within the tolerance are accepted and made exactly orthonormal.
    let text = GOOD.replacen("col_dir = [-1, 0, 0]", "col_dir = [-0.7071, 0.7071, 0]", 1);
    let (rig, _) = parse(&text).unwrap();
    let f = &rig.faces[1];
    assert!((f.col_dir.norm() - 1.0).abs() < 1e-15 && f.col_dir.dot(&f.row_dir).abs() < 1e-15);
}

#[test]
fn toml_syntax_and_type_errors_carry_line_and_column() {
    let e = err(&GOOD.replacen("cols = 6", "cols = = 6", 1));
    assert!(matches!(e, RigError::Syntax { .. }));
    let msg = chain(&e);
    assert!(
        msg.starts_with("rig.toml: not a valid rig description | "),
        "{msg}"
    );
    assert!(msg.contains("line 14"), "{msg}");
    let msg = chain(&err(&GOOD.replacen("cols = 6", "cols = \"six\"", 1)));
    assert!(msg.contains("line 14") && msg.contains("cols"), "{msg}");
    let msg = chain(&err(&GOOD.replacen("cols = 6", "cols = 6\ncolz = 7", 1)));
    assert!(msg.contains("colz") && msg.contains("line 15"), "{msg}");
    let msg = chain(&err(&GOOD.replacen(
        "origin = [160, 0, 40]",
        "origin = [160, 0]",
        1,
    )));
    assert!(msg.contains("line 17") && msg.contains("length 3"), "{msg}");
}

#[test]
fn overlapping_faces_are_rejected() {
    // Coplanar boards sharing area.
    let e = err(&GOOD
        .replacen("origin = [160, 0, 40]", "origin = [0, 100, 40]", 1)
        .replacen("col_dir = [-1, 0, 0]", "col_dir = [0, 1, 0]", 1));
    assert!(
        matches!(&e, RigError::FacesOverlap { a, b, .. } if a == "left" && b == "right"),
        "{e:?}"
    );
    assert!(e.to_string().contains("coplanar"), "{e}");
    // Boards crossing each other: the right wall moved to y = 60 cuts through the left wall's board.
    let e = err(&GOOD
        .replacen("origin = [160, 0, 40]", "origin = [160, 60, 40]", 1)
        .replacen("origin = [0, 40, 40]", "origin = [40, 40, 40]", 1));
    assert!(e.to_string().contains("cross each other"), "{e}");
    // Boards meeting along an edge (a closed corner: both outlines end on the line x = y = 0) are fine.
    let text = GOOD.replacen("origin = [160, 0, 40]", "origin = [140, 0, 40]", 1);
    let (rig, _) = parse(&text).unwrap();
    assert_eq!(rig.faces[0].outline()[0].y, 0.0);
    assert!(rig.faces[1].outline().iter().any(|p| p.x == 0.0));
}

#[test]
fn unreadable_file_names_the_path() {
    let e = Rig::load(Path::new("/nonexistent/rig.toml")).unwrap_err();
    assert_eq!(e.to_string(), "cannot read rig file /nonexistent/rig.toml");
    assert_eq!(e.exit_code(), cubecal::exit::BAD_INPUT);
}

// ---- SVG ----

/// Attributes of every `<rect .../>` element, in order.
fn rects(svg: &str) -> Vec<std::collections::HashMap<String, String>> {
    svg.split("<rect ")
        .skip(1)
        .map(|r| {
            let body = &r[..r.find("/>").unwrap()];
            let mut attrs = std::collections::HashMap::new();
            let mut rest = body;
            while let Some(eq) = rest.find("=\"") {
                let key = rest[..eq].trim().to_string();
                let after = &rest[eq + 2..];
                let end = after.find('"').unwrap();
                attrs.insert(key, after[..end].to_string());
                rest = &after[end + 1..];
            }
            attrs
        })
        .collect()
}

fn num(attrs: &std::collections::HashMap<String, String>, k: &str) -> f64 {
    attrs[k].parse().unwrap()
}

fn svg_attr(svg: &str, k: &str) -> String {
    let tag = &svg[svg.find("<svg ").unwrap()..];
    let start = tag.find(&format!(" {k}=\"")).unwrap() + k.len() + 3;
    tag[start..start + tag[start..].find('"').unwrap()].to_string()
}

#[test]
fn svg_geometry_matches_the_rig_at_physical_scale() {
    let (rig, _) = load("cube_outside.toml");
    for face in &rig.faces {
        let svg = face_svg(&rig, face);
        let lay = PageLayout::for_face(face);
        // Physical size in mm, viewBox in mm.
        let w = svg_attr(&svg, "width");
        let h = svg_attr(&svg, "height");
        assert!(w.ends_with("mm") && h.ends_with("mm"));
        let (w, h): (f64, f64) = (
            w.trim_end_matches("mm").parse().unwrap(),
            h.trim_end_matches("mm").parse().unwrap(),
        );
        assert_eq!(svg_attr(&svg, "viewBox"), format!("0 0 {w:.4} {h:.4}"));
        assert!((w - lay.page_width_mm).abs() < 1e-3 && (h - lay.page_height_mm).abs() < 1e-3);
        let all = rects(&svg);
        // Board outline: squares plus margins.
        let board = all
            .iter()
            .find(|r| r.get("id").is_some_and(|v| v == "board"))
            .unwrap();
        let s = face.square_mm;
        let m = face.margin_mm;
        assert!((num(board, "width") - ((face.cols + 1) as f64 * s + 2.0 * m)).abs() < 1e-3);
        assert!((num(board, "height") - ((face.rows + 1) as f64 * s + 2.0 * m)).abs() < 1e-3);
        let (bx, by) = (num(board, "x"), num(board, "y"));
        // Squares: one rect per black square, at its exact place (rows run up the page).
        let squares: Vec<_> = all.iter().filter(|r| r.contains_key("data-row")).collect();
        let n_black = (0..=face.rows)
            .flat_map(|i| (0..=face.cols).map(move |j| (i, j)))
            .filter(|&(i, j)| face.square_colour(i, j) == SquareColour::Black)
            .count();
        assert_eq!(squares.len(), n_black);
        for r in squares {
            let (i, j): (usize, usize) = (
                r["data-row"].parse().unwrap(),
                r["data-col"].parse().unwrap(),
            );
            assert_eq!(face.square_colour(i, j), SquareColour::Black);
            assert!((num(r, "width") - s).abs() < 1e-3 && (num(r, "height") - s).abs() < 1e-3);
            let x = bx + m + j as f64 * s;
            let y = by + m + (face.rows - i) as f64 * s;
            assert!((num(r, "x") - x).abs() < 1e-3, "square ({i}, {j}) x");
            assert!((num(r, "y") - y).abs() < 1e-3, "square ({i}, {j}) y");
        }
        let bar = all
            .iter()
            .find(|r| r.get("id").is_some_and(|v| v == "scale-bar"))
            .unwrap();
        assert_eq!(num(bar, "width"), SCALE_BAR_MM);
        assert_eq!(SCALE_BAR_MM, 100.0);
        // The bar and the label sit below the board, on the page.
        assert!(num(bar, "y") > by + num(board, "height"));
        assert!(num(bar, "x") + 100.0 <= w);
        assert!(
            svg.contains(&format!("/ {}: ", face.name)) && svg.contains(&format!("squares {s} mm"))
        );
        // The margin label lies inside the board's bottom margin.
        let label = &svg[svg.find("id=\"margin-label\"").unwrap()..];
        let label_y: f64 = label[label.find(" y=\"").unwrap() + 4..]
            .split('"')
            .next()
            .unwrap()
            .parse()
            .unwrap();
        assert!(label_y > by + num(board, "height") - m && label_y < by + num(board, "height"));
        assert!(label.contains(&format!("{}: {s} mm squares", face.name)));
    }
}

#[test]
fn cli_target_print_writes_one_svg_per_face() {
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["rig", "print"])
        .arg(fixture("inside_corner.toml"))
        .arg("--out")
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    for name in ["floor", "wall-x", "wall-y"] {
        let text = std::fs::read_to_string(dir.path().join(format!("{name}.svg"))).unwrap();
        assert!(text.contains("<svg ") && text.contains("scale-bar"));
    }
    // A bad rig file exits with the bad-input code and names the key.
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, GOOD.replacen("square_mm = 20.0", "square_mm = -5", 1)).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_cubecal"))
        .args(["target", "print"])
        .arg(&bad)
        .arg("--out")
        .arg(dir.path())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(i32::from(cubecal::exit::BAD_INPUT)));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("bad.toml: faces[0].square_mm: expected a positive length in mm, got -5"),
        "{stderr}"
    );
}
