//! Printable boards: one SVG per face at exact physical scale.
//!
//! The SVG's user unit is the millimetre (`width="…mm"`, `height="…mm"`, `viewBox` in mm), so printing
//! at 100 % reproduces the rig. The page holds the board (squares plus white margin, outlined by a thin
//! grey cut line; the face name and square size are printed small in the bottom margin when it is at
//! least 3 mm wide) and, below it, a label strip with the rig and face names, the square size and a
//! 100 mm scale bar for checking the printer's scale.
//!
//! Orientation: the board is drawn as seen from the front (from the side its normal points to).
//! Because the normal is `col_dir × row_dir`, columns then run to the right and rows run *up*: inner
//! corner `(0, 0)` is at the bottom left of the pattern.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::charuco::Charuco;
use super::{Face, Rig, RigError, SquareColour};

/// Height of the label strip below the board, mm.
pub const LABEL_STRIP_MM: f64 = 22.0;
/// Length of the scale bar, mm.
pub const SCALE_BAR_MM: f64 = 100.0;
/// Blank border around everything on the page, mm.
pub const PAGE_BORDER_MM: f64 = 5.0;

/// Placement of a face's board on its SVG page (all mm, SVG coordinates: x right, y down).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PageLayout {
    pub page_width_mm: f64,
    pub page_height_mm: f64,
    /// Top-left corner of the board outline (margin included).
    pub board_x_mm: f64,
    pub board_y_mm: f64,
    pub board_width_mm: f64,
    pub board_height_mm: f64,
}

impl PageLayout {
    /// The layout used by [`face_svg`].
    pub fn for_face(face: &Face) -> Self {
        let ([a0, a1], [b0, b1]) = face.board_extent();
        let (bw, bh) = (a1 - a0, b1 - b0);
        let page_width_mm = bw.max(SCALE_BAR_MM + 10.0) + 2.0 * PAGE_BORDER_MM;
        PageLayout {
            page_width_mm,
            page_height_mm: bh + LABEL_STRIP_MM + 2.0 * PAGE_BORDER_MM,
            board_x_mm: (page_width_mm - bw) / 2.0,
            board_y_mm: PAGE_BORDER_MM,
            board_width_mm: bw,
            board_height_mm: bh,
        }
    }

    /// SVG position of face coordinates `(a, b)` (mm from inner corner (0, 0)).
    pub fn to_svg(&self, face: &Face, a: f64, b: f64) -> (f64, f64) {
        let ([a0, _], [_, b1]) = face.board_extent();
        (self.board_x_mm + (a - a0), self.board_y_mm + (b1 - b))
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// The SVG document of one face.
pub fn face_svg(rig: &Rig, face: &Face) -> String {
    let lay = PageLayout::for_face(face);
    let s = face.square_mm;
    let mut out = String::new();
    // Writing to a String cannot fail.
    let _ = writeln!(out, r#"<?xml version="1.0" encoding="UTF-8"?>"#);
    let _ = writeln!(
        out,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w:.4}mm" height="{h:.4}mm" viewBox="0 0 {w:.4} {h:.4}">"#,
        w = lay.page_width_mm,
        h = lay.page_height_mm
    );
    let _ = writeln!(
        out,
        r#"<rect id="page" x="0" y="0" width="{:.4}" height="{:.4}" fill="white"/>"#,
        lay.page_width_mm, lay.page_height_mm
    );
    let _ = writeln!(
        out,
        "<rect id=\"board\" x=\"{:.4}\" y=\"{:.4}\" width=\"{:.4}\" height=\"{:.4}\" fill=\"none\" stroke=\"#b0b0b0\" stroke-width=\"0.1\"/>",
        lay.board_x_mm, lay.board_y_mm, lay.board_width_mm, lay.board_height_mm
    );
    let _ = writeln!(
        out,
        r#"<g id="squares" fill="black" shape-rendering="crispEdges">"#
    );
    for i in 0..=face.rows {
        for j in 0..=face.cols {
            if face.square_colour(i, j) != SquareColour::Black {
                continue;
            }
            // Square (i, j) spans a ∈ [(j−1)s, js], b ∈ [(i−1)s, is]; its SVG top-left is (a_min, b_max).
            let (x, y) = lay.to_svg(face, (j as f64 - 1.0) * s, i as f64 * s);
            let _ = writeln!(
                out,
                r#"<rect data-row="{i}" data-col="{j}" x="{x:.4}" y="{y:.4}" width="{s:.4}" height="{s:.4}"/>"#
            );
        }
    }
    let _ = writeln!(out, "</g>");
    if let Some(ch) = &face.charuco {
        markers_svg(&mut out, face, ch, &lay);
    }
    // Face name and square size in the board's own bottom margin, when there is room, so that the
    // information stays with the board after it is cut out.
    if face.margin_mm >= 3.0 {
        let size = (face.margin_mm * 0.5).min(4.0);
        let _ = writeln!(
            out,
            r#"<text id="margin-label" x="{:.4}" y="{:.4}" font-family="sans-serif" font-size="{size:.4}" fill="dimgray">{}: {} mm squares</text>"#,
            lay.board_x_mm + face.margin_mm,
            lay.board_y_mm + lay.board_height_mm - (face.margin_mm - size * 0.7) / 2.0,
            escape(&face.name),
            s
        );
    }
    let text_x = PAGE_BORDER_MM;
    let line1_y = lay.board_y_mm + lay.board_height_mm + 6.0;
    let _ = writeln!(
        out,
        r#"<text id="label" x="{text_x:.4}" y="{line1_y:.4}" font-family="sans-serif" font-size="3.5">{} / {}: {}×{} inner corners, squares {} mm</text>"#,
        escape(&rig.name),
        escape(&face.name),
        face.cols,
        face.rows,
        s
    );
    let bar_y = line1_y + 5.0;
    let _ = writeln!(out, r#"<g id="scale">"#);
    let _ = writeln!(
        out,
        r#"<rect id="scale-bar" x="{text_x:.4}" y="{bar_y:.4}" width="{SCALE_BAR_MM:.4}" height="1.5" fill="black"/>"#
    );
    for cm in 0..=10 {
        let x = text_x + f64::from(cm) * 10.0;
        let _ = writeln!(
            out,
            r#"<rect x="{:.4}" y="{:.4}" width="0.2" height="3" fill="black"/>"#,
            x - 0.1,
            bar_y - 1.5
        );
    }
    let _ = writeln!(
        out,
        r#"<text x="{:.4}" y="{:.4}" font-family="sans-serif" font-size="3">100 mm (check after printing at 100 %); corner (0,0) at bottom left</text>"#,
        text_x,
        bar_y + 6.0
    );
    let _ = writeln!(out, "</g>");
    let _ = writeln!(out, "</svg>");
    out
}

/// A ChArUco face's markers: each black cell (border and 0 bits) of each white square's marker.
fn markers_svg(out: &mut String, face: &Face, ch: &Charuco, lay: &PageLayout) {
    let s = face.square_mm;
    let n = ch.dictionary.bits;
    let cell = ch.marker_mm / (n + 2) as f64;
    let d = (s - ch.marker_mm) / 2.0;
    let _ = writeln!(
        out,
        r#"<g id="markers" fill="black" shape-rendering="crispEdges" data-dictionary="{}">"#,
        ch.dictionary.name()
    );
    for y in 0..=face.rows {
        for x in 0..=face.cols {
            let Some(id) = Charuco::marker_index(face.cols, x, y).and_then(|k| ch.ids.get(k))
            else {
                continue;
            };
            let Some(code) = ch.dictionary.code(*id) else {
                continue;
            };
            let _ = writeln!(out, r#"<g data-id="{id}">"#);
            for r in 0..n + 2 {
                for c in 0..n + 2 {
                    let border = r == 0 || c == 0 || r == n + 1 || c == n + 1;
                    if !border && ch.dictionary.bit(code, r - 1, c - 1) {
                        continue;
                    }
                    // OpenCV board coordinates (y down from the top) of the cell's top-left corner.
                    let x_cv = x as f64 * s + d + c as f64 * cell;
                    let y_cv = y as f64 * s + d + r as f64 * cell;
                    let (sx, sy) = lay.to_svg(face, x_cv - s, face.rows as f64 * s - y_cv);
                    let _ = writeln!(
                        out,
                        r#"<rect x="{sx:.4}" y="{sy:.4}" width="{cell:.4}" height="{cell:.4}"/>"#
                    );
                }
            }
            let _ = writeln!(out, "</g>");
        }
    }
    let _ = writeln!(out, "</g>");
}

/// File name used for a face's SVG: the face name made file-safe.
pub fn face_file_name(face: &Face) -> String {
    let safe: String = face
        .name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect();
    format!("{safe}.svg")
}

/// Write one SVG per face into `dir` (created if needed), atomically per file; returns the paths.
pub fn write_face_svgs(rig: &Rig, dir: &Path) -> Result<Vec<PathBuf>, RigError> {
    std::fs::create_dir_all(dir).map_err(|source| RigError::Write {
        path: dir.display().to_string(),
        source,
    })?;
    let mut paths = Vec::new();
    for face in &rig.faces {
        let path = dir.join(face_file_name(face));
        write_atomic(&path, face_svg(rig, face).as_bytes()).map_err(|source| RigError::Write {
            path: path.display().to_string(),
            source,
        })?;
        tracing::info!(face = %face.name, path = %path.display(), "wrote printable board");
        paths.push(path);
    }
    Ok(paths)
}

/// Write through a temporary file in the same directory, then rename over `path`.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let mut builder = tempfile::Builder::new();
    // Results are ordinary files for the user (subject to the umask), not private temporaries.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o644));
    }
    let mut tmp = builder.tempfile_in(dir)?;
    tmp.write_all(bytes)?;
    tmp.as_file().sync_all()?;
    tmp.persist(path).map_err(|e| e.error)?;
    Ok(())
}
