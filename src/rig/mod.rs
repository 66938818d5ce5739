//! Rig descriptions: one or more flat checkerboard faces fixed in a common 3D frame (the *rig frame*,
//! millimetres), loaded from TOML.
//!
//! ## File format
//! ```toml
//! name = "cube-outside"
//! units = "mm"                 # the only unit supported
//! up = [0, 0, 1]               # optional: the rig's vertical (turntable axis), rig frame
//! [body]                       # optional: a solid box the boards are mounted on (drawn in body shade)
//! min = [0, 0, 0]
//! max = [200, 200, 200]
//! [[faces]]
//! name = "top"
//! cols = 9                     # inner corners along a row (along col_dir)
//! rows = 6                     # inner corners along a column (along row_dir)
//! square_mm = 16.0
//! origin = [36, 56, 200]       # rig-frame position of inner corner (row 0, col 0)
//! col_dir = [1, 0, 0]          # direction of increasing column
//! row_dir = [0, 1, 0]          # direction of increasing row
//! margin_mm = 10.0             # optional white border around the squares (default: one square)
//! first_square = "black"       # optional colour of square (0, 0) (default: black)
//! open_sides = ["first_row"]   # optional: sides where the printed pattern runs on beyond the corners
//!                              # described (a board larger than any view shows; see below)
//! ```
//!
//! A ChArUco face (OpenCV's layout, see [`charuco`]) adds one key; its squares' colours then follow
//! OpenCV's layout (`first_square` may not contradict it) and it has no `open_sides`:
//! ```toml
//! charuco = { dictionary = "DICT_5X5_250", marker_mm = 15.0, first_id = 0 }  # or ids = [...]
//! ```
//! `ids` lists the markers in OpenCV's order (white squares row by row from the top of the printed
//! board); `first_id` numbers them consecutively. An id is used once in a rig per marker size.
//!
//! ## Face geometry
//! Inner corner `(row r, col c)` is at `origin + c·square·col_dir + r·square·row_dir`. Squares are
//! indexed `(i, j)` with `i ∈ 0..=rows`, `j ∈ 0..=cols`; square `(i, j)` spans face coordinates
//! `a ∈ [(j−1)·s, j·s]` along `col_dir` and `b ∈ [(i−1)·s, i·s]` along `row_dir`, so square `(0, 0)` is
//! the one diagonally before corner `(0, 0)`, and its colour alternates from `first_square`. The
//! face **normal** is `col_dir × row_dir` and points out of the printed side, toward the viewer.
//!
//! ## Open sides
//! `open_sides` lists the sides of a face (`first_row`, `last_row`, `first_col`, `last_col`: the
//! outermost row or column of inner corners) beyond which the printed pattern continues further than
//! the rig describes — a board that runs off every view, whose true end is never seen. `rows`/`cols`
//! then count only the corners described, and the detector never takes a grid's end for that side:
//! such a face is labelled only by the sides where its pattern visibly ends (a margin, a seam or a
//! fold), never by its size. Each side at most once; at least one side must stay closed on each axis.
//!
//! Parsing follows "parse, then validate": the TOML lands in plain serde structs whose fields are all
//! optional ([`RawRig`]); validation turns them into [`Rig`] and names every bad key by its path
//! (`rig.toml: faces[2].cols: expected an integer ≥ 2, got -3`). Direction vectors must be unit length
//! and orthogonal within [`ORTHONORMAL_TOLERANCE`]; they are then re-orthonormalised exactly.

pub mod charuco;
pub mod survey;
pub mod svg;

pub(crate) use svg::write_atomic;

use std::path::Path;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// How far from unit length / orthogonality a face's direction vectors may be before the rig is rejected.
/// Within it, the directions are re-orthonormalised (Gram–Schmidt) so that hand-typed values such as
/// `0.7071` work.
pub const ORTHONORMAL_TOLERANCE: f64 = 1e-3;

/// Two geometric features closer than this (mm) count as touching rather than crossing.
pub const GEOMETRY_TOLERANCE_MM: f64 = 1e-3;

/// The inner-corner count of a plain chessboard, `COLSxROWS` as OpenCV's `patternSize` (a board of
/// 10 × 7 squares is `9x6`): the `--board` of `cubecal calibrate` and `cubecal detect`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoardSize {
    /// Inner corners along a row.
    pub cols: u32,
    /// Inner corners along a column.
    pub rows: u32,
}

/// A `--board` value that is not `COLSxROWS` with both counts at least 2.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "'{0}' is not COLSxROWS inner corners, each at least 2 (e.g. 9x6 for a board of 10 × 7 squares)"
)]
pub struct BoardSizeError(pub String);

impl std::str::FromStr for BoardSize {
    type Err = BoardSizeError;
    fn from_str(s: &str) -> Result<BoardSize, BoardSizeError> {
        let bad = || BoardSizeError(s.to_string());
        let (c, r) = s.split_once(['x', 'X', '×']).ok_or_else(bad)?;
        let parse = |t: &str| t.trim().parse::<u32>().ok().filter(|n| *n >= 2);
        Ok(BoardSize {
            cols: parse(c).ok_or_else(bad)?,
            rows: parse(r).ok_or_else(bad)?,
        })
    }
}

impl std::fmt::Display for BoardSize {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}x{}", self.cols, self.rows)
    }
}

/// The rig file of a flat chessboard of `size` inner corners and `square_mm` squares: one face in
/// the rig's z = 0 plane, inner corner (0, 0) at the origin, columns along +x, rows along +y, the
/// default margin of one square. Parse it with [`Rig::from_toml_str`] (which checks `square_mm`).
pub fn board_toml(size: BoardSize, square_mm: f64) -> String {
    format!(
        "# A plain chessboard given as --board {size} --square {square_mm}\n\
         name = \"board-{size}-{square_mm}mm\"\n\
         units = \"mm\"\n\n\
         [[faces]]\n\
         name = \"board\"\n\
         cols = {}\n\
         rows = {}\n\
         square_mm = {square_mm:?}\n\
         origin = [0, 0, 0]\n\
         col_dir = [1, 0, 0]\n\
         row_dir = [0, 1, 0]\n",
        size.cols, size.rows
    )
}

/// Errors loading or validating a rig description. `path` is the file (or the name given to
/// [`Rig::from_toml_str`]); `key` is the TOML key path such as `faces[2].cols`.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    #[error("cannot read rig file {path}")]
    Read {
        path: String,
        #[source]
        source: std::io::Error,
    },
    /// TOML syntax error, wrong value type or unknown key; the cause carries line and column.
    #[error("{path}: not a valid rig description")]
    Syntax {
        path: String,
        #[source]
        source: toml::de::Error,
    },
    #[error("{path}: {key}: missing")]
    Missing { path: String, key: String },
    #[error("{path}: {key}: expected {expected}, got {value}")]
    Invalid {
        path: String,
        key: String,
        expected: String,
        value: String,
    },
    #[error(
        "{path}: faces[{index}] ({face}): col_dir and row_dir must be orthonormal ({detail}; tolerance {ORTHONORMAL_TOLERANCE})"
    )]
    NotOrthonormal {
        path: String,
        index: usize,
        face: String,
        detail: String,
    },
    #[error("{path}: faces '{a}' and '{b}' overlap ({detail})")]
    FacesOverlap {
        path: String,
        a: String,
        b: String,
        detail: String,
    },
    #[error("cannot write {path}")]
    Write {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

impl RigError {
    /// The process exit code for this error (see [`crate::exit`]).
    pub fn exit_code(&self) -> u8 {
        match self {
            RigError::Read { .. }
            | RigError::Syntax { .. }
            | RigError::Missing { .. }
            | RigError::Invalid { .. }
            | RigError::NotOrthonormal { .. }
            | RigError::FacesOverlap { .. } => crate::exit::BAD_INPUT,
            RigError::Write { .. } => crate::exit::INTERNAL,
        }
    }
}

/// Something legal but worth knowing about a rig; returned by [`Rig::load`] and logged.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum RigWarning {
    /// The face's pattern maps onto itself under a 180° rotation (`cols + rows` even): from the face
    /// alone its orientation is ambiguous.
    SymmetricGrid {
        face: String,
        cols: usize,
        rows: usize,
    },
    /// Two faces have the same grid size, so a detector cannot tell them apart by size.
    SameGridSize { a: String, b: String },
}

impl std::fmt::Display for RigWarning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RigWarning::SymmetricGrid { face, cols, rows } => write!(
                f,
                "face '{face}': a {cols}×{rows} grid looks the same rotated by 180°, so its orientation \
                 is ambiguous unless the rig geometry breaks the symmetry (use cols + rows odd to avoid this)"
            ),
            RigWarning::SameGridSize { a, b } => write!(
                f,
                "faces '{a}' and '{b}' have the same grid size; a detector cannot tell them apart by size"
            ),
        }
    }
}

/// Colour of a checkerboard square.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SquareColour {
    Black,
    White,
}

impl SquareColour {
    /// The other colour.
    pub fn flipped(self) -> Self {
        match self {
            SquareColour::Black => SquareColour::White,
            SquareColour::White => SquareColour::Black,
        }
    }
}

/// One validated checkerboard face.
#[derive(Debug, Clone, PartialEq)]
pub struct Face {
    pub name: String,
    /// Inner corners along `col_dir`.
    pub cols: usize,
    /// Inner corners along `row_dir`.
    pub rows: usize,
    pub square_mm: f64,
    /// White border around the squares.
    pub margin_mm: f64,
    /// Rig-frame position of inner corner `(0, 0)`.
    pub origin: Vector3<f64>,
    /// Unit direction of increasing column.
    pub col_dir: Vector3<f64>,
    /// Unit direction of increasing row (orthogonal to `col_dir`).
    pub row_dir: Vector3<f64>,
    /// Colour of square `(0, 0)`.
    pub first_square: SquareColour,
    /// Sides beyond which the pattern continues further than described (see the module docs).
    pub open_sides: Vec<FaceSide>,
    /// Set for a ChArUco face: markers in its white squares ([`charuco`]).
    pub charuco: Option<charuco::Charuco>,
}

/// A side of a face: its outermost row or column of inner corners.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FaceSide {
    FirstRow,
    LastRow,
    FirstCol,
    LastCol,
}

impl FaceSide {
    pub const ALL: [FaceSide; 4] = [
        FaceSide::FirstRow,
        FaceSide::LastRow,
        FaceSide::FirstCol,
        FaceSide::LastCol,
    ];

    /// The key's spelling in a rig file.
    pub fn as_str(self) -> &'static str {
        match self {
            FaceSide::FirstRow => "first_row",
            FaceSide::LastRow => "last_row",
            FaceSide::FirstCol => "first_col",
            FaceSide::LastCol => "last_col",
        }
    }

    /// The side across the face.
    pub fn opposite(self) -> FaceSide {
        match self {
            FaceSide::FirstRow => FaceSide::LastRow,
            FaceSide::LastRow => FaceSide::FirstRow,
            FaceSide::FirstCol => FaceSide::LastCol,
            FaceSide::LastCol => FaceSide::FirstCol,
        }
    }
}

/// Where a point of a face's plane falls on the printed board.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum BoardRegion {
    /// Square `(i, j)` (`i ∈ 0..=rows`, `j ∈ 0..=cols`).
    Square { i: usize, j: usize },
    /// The white margin.
    Margin,
    /// Outside the board.
    Outside,
}

impl Face {
    /// Rig-frame position of the lattice point `(row, col)`, which may lie outside the face's inner
    /// corners (negative or beyond `rows`/`cols`): e.g. one step beyond a side.
    pub fn lattice_xyz(&self, row: f64, col: f64) -> Vector3<f64> {
        self.origin + self.col_dir * (col * self.square_mm) + self.row_dir * (row * self.square_mm)
    }

    /// Whether the pattern runs on beyond `side` (listed in `open_sides`).
    pub fn is_open(&self, side: FaceSide) -> bool {
        self.open_sides.contains(&side)
    }

    /// Rig-frame position of inner corner `(row, col)`.
    pub fn corner_xyz(&self, row: usize, col: usize) -> Vector3<f64> {
        self.origin
            + self.col_dir * (col as f64 * self.square_mm)
            + self.row_dir * (row as f64 * self.square_mm)
    }

    /// Unit normal `col_dir × row_dir`, pointing out of the printed side toward the viewer.
    pub fn normal(&self) -> Vector3<f64> {
        self.col_dir.cross(&self.row_dir)
    }

    /// Number of inner corners.
    pub fn n_corners(&self) -> usize {
        self.cols * self.rows
    }

    /// Colour of square `(i, j)` (row `i ∈ 0..=rows`, column `j ∈ 0..=cols`).
    pub fn square_colour(&self, i: usize, j: usize) -> SquareColour {
        if (i + j).is_multiple_of(2) {
            self.first_square
        } else {
            self.first_square.flipped()
        }
    }

    /// Whether the printed pattern maps onto itself under a 180° rotation: square `(i, j)` goes to
    /// `(rows − i, cols − j)`, which has the same colour for every square exactly when `rows + cols` is even.
    pub fn is_point_symmetric(&self) -> bool {
        (self.rows + self.cols).is_multiple_of(2)
    }

    /// The printed colour at face coordinates `(a, b)` (mm from inner corner `(0, 0)`), `None`
    /// outside the board: the square's colour, white in the margin, and on a ChArUco face the
    /// markers' cells in its white squares.
    pub fn ink_at(&self, a: f64, b: f64) -> Option<SquareColour> {
        match self.region_at(a, b) {
            BoardRegion::Outside => None,
            BoardRegion::Margin => Some(SquareColour::White),
            BoardRegion::Square { i, j } => {
                let colour = self.square_colour(i, j);
                let Some(ch) = &self.charuco else {
                    return Some(colour);
                };
                if colour == SquareColour::Black {
                    return Some(colour);
                }
                let (x, y) = charuco::opencv_square(self.rows, i, j);
                let id = charuco::Charuco::marker_index(self.cols, x, y)
                    .and_then(|k| ch.ids.get(k).copied());
                let s = self.square_mm;
                // OpenCV board coordinates: x from the left edge of the squares, y down from the top.
                let (bx, by) = (a + s, self.rows as f64 * s - b);
                Some(match id {
                    Some(id) if ch.marker_ink(s, x, y, id, bx, by) => SquareColour::Black,
                    _ => SquareColour::White,
                })
            }
        }
    }

    /// Face coordinates `(a, b)` in mm of a rig-frame point: `a` along `col_dir`, `b` along `row_dir`,
    /// from inner corner `(0, 0)`.
    pub fn local(&self, p: &Vector3<f64>) -> (f64, f64) {
        let d = p - self.origin;
        (d.dot(&self.col_dir), d.dot(&self.row_dir))
    }

    /// Extent of the squares in face coordinates: `([a_min, a_max], [b_min, b_max])`.
    pub fn pattern_extent(&self) -> ([f64; 2], [f64; 2]) {
        let s = self.square_mm;
        ([-s, self.cols as f64 * s], [-s, self.rows as f64 * s])
    }

    /// Extent of the whole board (squares plus margin) in face coordinates.
    pub fn board_extent(&self) -> ([f64; 2], [f64; 2]) {
        let ([a0, a1], [b0, b1]) = self.pattern_extent();
        let m = self.margin_mm;
        ([a0 - m, a1 + m], [b0 - m, b1 + m])
    }

    /// The board's outline including the margin, as four rig-frame points in order
    /// (`(a_min, b_min)`, `(a_max, b_min)`, `(a_max, b_max)`, `(a_min, b_max)`).
    pub fn outline(&self) -> [Vector3<f64>; 4] {
        let ([a0, a1], [b0, b1]) = self.board_extent();
        [(a0, b0), (a1, b0), (a1, b1), (a0, b1)]
            .map(|(a, b)| self.origin + self.col_dir * a + self.row_dir * b)
    }

    /// What is printed at face coordinates `(a, b)`.
    pub fn region_at(&self, a: f64, b: f64) -> BoardRegion {
        let s = self.square_mm;
        let ([a0, a1], [b0, b1]) = self.board_extent();
        if !(a >= a0 && a < a1 && b >= b0 && b < b1) {
            return BoardRegion::Outside;
        }
        let j = (a / s).floor() + 1.0;
        let i = (b / s).floor() + 1.0;
        if j >= 0.0 && j <= self.cols as f64 && i >= 0.0 && i <= self.rows as f64 {
            BoardRegion::Square {
                i: i as usize,
                j: j as usize,
            }
        } else {
            BoardRegion::Margin
        }
    }
}

/// An optional solid box (rig frame, mm) the boards are mounted on, such as the cube's body.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodyBox {
    pub min: Vector3<f64>,
    pub max: Vector3<f64>,
}

/// Identifies one inner corner of a rig.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct CornerId {
    pub face: usize,
    pub row: usize,
    pub col: usize,
}

/// A validated rig.
#[derive(Debug, Clone, PartialEq)]
pub struct Rig {
    pub name: String,
    /// Unit vertical of the rig (the turntable axis direction), rig frame.
    pub up: Vector3<f64>,
    pub body: Option<BodyBox>,
    pub faces: Vec<Face>,
}

/// The TOML as written: every field optional so that a missing key is reported by its path.
/// (Serialised by [`survey`] to write a surveyed rig.)
#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct RawRig {
    pub name: Option<String>,
    pub units: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub up: Option<[f64; 3]>,
    /// How the rig was surveyed (informational: written by `cubecal rig survey`, not used).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub survey: Option<survey::RigSurvey>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub body: Option<RawBody>,
    pub faces: Option<Vec<RawFace>>,
}

/// `[body]` as written.
#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct RawBody {
    pub min: Option<[f64; 3]>,
    pub max: Option<[f64; 3]>,
}

/// One `[[faces]]` entry as written.
#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct RawFace {
    pub name: Option<String>,
    pub cols: Option<i64>,
    pub rows: Option<i64>,
    pub square_mm: Option<f64>,
    pub origin: Option<[f64; 3]>,
    pub col_dir: Option<[f64; 3]>,
    pub row_dir: Option<[f64; 3]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub margin_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub first_square: Option<SquareColour>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub open_sides: Option<Vec<String>>,
    /// The face's surveyed deviation from the nominal rig file (informational, not used).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub survey: Option<survey::FaceSurvey>,
    /// A ChArUco face's markers.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub charuco: Option<RawCharuco>,
}

/// `[faces.charuco]` as written.
#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct RawCharuco {
    pub dictionary: Option<String>,
    pub marker_mm: Option<f64>,
    /// The first of consecutive ids (default 0), unless `ids` lists them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub first_id: Option<i64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ids: Option<Vec<i64>>,
}

impl Rig {
    /// Read, parse and validate a rig file; warnings are also logged.
    pub fn load(path: &Path) -> Result<(Rig, Vec<RigWarning>), RigError> {
        let (rig, warnings) = Rig::read_quiet(path)?;
        rig.log_warnings(&warnings);
        Ok((rig, warnings))
    }

    /// [`Rig::load`] without logging the warnings: for readers of a rig whose warnings were told
    /// when it was used (a run's `rig.toml` read again for its report).
    pub fn read_quiet(path: &Path) -> Result<(Rig, Vec<RigWarning>), RigError> {
        let text = std::fs::read_to_string(path).map_err(|source| RigError::Read {
            path: path.display().to_string(),
            source,
        })?;
        Rig::from_toml_str(&text, &path.display().to_string())
    }

    /// Parse and validate rig TOML; `path` names the source in errors. The warnings are returned,
    /// not logged: the caller tells them once ([`Rig::log_warnings`]).
    pub fn from_toml_str(text: &str, path: &str) -> Result<(Rig, Vec<RigWarning>), RigError> {
        let raw: RawRig = toml::from_str(text).map_err(|source| RigError::Syntax {
            path: path.to_string(),
            source,
        })?;
        raw.validate(path)
    }

    /// Log a rig's warnings (once per use of the rig, on stderr at the default level).
    pub fn log_warnings(&self, warnings: &[RigWarning]) {
        for w in warnings {
            tracing::warn!(rig = %self.name, "{w}");
        }
    }

    /// Rig-frame position of inner corner `(row, col)` of face `face`, or `None` if out of range.
    pub fn corner_xyz(&self, face: usize, row: usize, col: usize) -> Option<Vector3<f64>> {
        let f = self.faces.get(face)?;
        (row < f.rows && col < f.cols).then(|| f.corner_xyz(row, col))
    }

    /// Every inner corner, face by face, row-major.
    pub fn corners(&self) -> impl Iterator<Item = CornerId> + '_ {
        self.faces.iter().enumerate().flat_map(|(fi, f)| {
            (0..f.rows)
                .flat_map(move |row| (0..f.cols).map(move |col| CornerId { face: fi, row, col }))
        })
    }

    /// Total number of inner corners.
    pub fn n_corners(&self) -> usize {
        self.faces.iter().map(Face::n_corners).sum()
    }

    /// Axis-aligned bounds of everything physical (board outlines and body), rig frame.
    pub fn bounds(&self) -> (Vector3<f64>, Vector3<f64>) {
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        let mut add = |p: &Vector3<f64>| {
            lo = lo.inf(p);
            hi = hi.sup(p);
        };
        for f in &self.faces {
            f.outline().iter().for_each(&mut add);
        }
        if let Some(b) = &self.body {
            add(&b.min);
            add(&b.max);
        }
        (lo, hi)
    }

    /// Centre of [`Rig::bounds`].
    pub fn centre(&self) -> Vector3<f64> {
        let (lo, hi) = self.bounds();
        (lo + hi) / 2.0
    }

    /// Radius of the sphere about [`Rig::centre`] enclosing every board corner and the body.
    pub fn radius(&self) -> f64 {
        let c = self.centre();
        let mut r: f64 = 0.0;
        for f in &self.faces {
            for p in f.outline() {
                r = r.max((p - c).norm());
            }
        }
        if let Some(b) = &self.body {
            for k in 0..8 {
                let p = Vector3::new(
                    if k & 1 == 0 { b.min.x } else { b.max.x },
                    if k & 2 == 0 { b.min.y } else { b.max.y },
                    if k & 4 == 0 { b.min.z } else { b.max.z },
                );
                r = r.max((p - c).norm());
            }
        }
        r
    }

    /// The direction from which the rig is meant to be seen: the mean of the unit face normals
    /// (unweighted, so that a cube with differently sized boards is seen along its diagonal), or `+z`
    /// if they cancel.
    pub fn viewing_direction(&self) -> Vector3<f64> {
        let n: Vector3<f64> = self.faces.iter().map(Face::normal).sum();
        n.try_normalize(1e-9).unwrap_or_else(Vector3::z)
    }
}

fn fmt_vec(v: &[f64; 3]) -> String {
    format!("[{}, {}, {}]", v[0], v[1], v[2])
}

impl RawRig {
    /// Validate into a [`Rig`] plus warnings; `path` names the source in errors.
    pub fn validate(self, path: &str) -> Result<(Rig, Vec<RigWarning>), RigError> {
        let missing = |key: &str| RigError::Missing {
            path: path.to_string(),
            key: key.to_string(),
        };
        let invalid = |key: &str, expected: &str, value: String| RigError::Invalid {
            path: path.to_string(),
            key: key.to_string(),
            expected: expected.to_string(),
            value,
        };
        let name = self.name.ok_or_else(|| missing("name"))?;
        if name.trim().is_empty() {
            return Err(invalid("name", "a non-empty name", format!("{name:?}")));
        }
        let units = self.units.ok_or_else(|| missing("units"))?;
        if units != "mm" {
            return Err(invalid("units", "\"mm\"", format!("{units:?}")));
        }
        let finite_vec = |key: &str, v: [f64; 3]| -> Result<Vector3<f64>, RigError> {
            if v.iter().all(|x| x.is_finite()) {
                Ok(Vector3::from(v))
            } else {
                Err(invalid(key, "three finite numbers", fmt_vec(&v)))
            }
        };
        let body = match self.body {
            None => None,
            Some(b) => {
                let min = finite_vec("body.min", b.min.ok_or_else(|| missing("body.min"))?)?;
                let max = finite_vec("body.max", b.max.ok_or_else(|| missing("body.max"))?)?;
                if (0..3).any(|k| !(max[k] > min[k])) {
                    return Err(invalid(
                        "body.max",
                        "every coordinate greater than body.min",
                        fmt_vec(&[max.x, max.y, max.z]),
                    ));
                }
                Some(BodyBox { min, max })
            }
        };
        let raw_faces = self.faces.ok_or_else(|| missing("faces"))?;
        if raw_faces.is_empty() {
            return Err(invalid(
                "faces",
                "at least one [[faces]] entry",
                "none".into(),
            ));
        }
        let mut faces: Vec<Face> = Vec::with_capacity(raw_faces.len());
        for (k, rf) in raw_faces.into_iter().enumerate() {
            let key = |field: &str| format!("faces[{k}].{field}");
            let name = rf.name.ok_or_else(|| missing(&key("name")))?;
            if let Some(other) = faces.iter().position(|f| f.name == name) {
                return Err(invalid(
                    &key("name"),
                    "a name unique within the rig",
                    format!("{name:?} (also faces[{other}])"),
                ));
            }
            let count = |field: &str, v: Option<i64>| -> Result<usize, RigError> {
                let v = v.ok_or_else(|| missing(&key(field)))?;
                if v < 2 {
                    return Err(invalid(
                        &key(field),
                        "a positive integer ≥ 2",
                        v.to_string(),
                    ));
                }
                usize::try_from(v)
                    .map_err(|_| invalid(&key(field), "a smaller integer", v.to_string()))
            };
            let cols = count("cols", rf.cols)?;
            let rows = count("rows", rf.rows)?;
            let square_mm = rf.square_mm.ok_or_else(|| missing(&key("square_mm")))?;
            if !(square_mm > 0.0 && square_mm.is_finite()) {
                return Err(invalid(
                    &key("square_mm"),
                    "a positive length in mm",
                    square_mm.to_string(),
                ));
            }
            let margin_mm = rf.margin_mm.unwrap_or(square_mm);
            if !(margin_mm >= 0.0 && margin_mm.is_finite()) {
                return Err(invalid(
                    &key("margin_mm"),
                    "a length ≥ 0 in mm",
                    margin_mm.to_string(),
                ));
            }
            let origin = finite_vec(
                &key("origin"),
                rf.origin.ok_or_else(|| missing(&key("origin")))?,
            )?;
            let col_dir = finite_vec(
                &key("col_dir"),
                rf.col_dir.ok_or_else(|| missing(&key("col_dir")))?,
            )?;
            let row_dir = finite_vec(
                &key("row_dir"),
                rf.row_dir.ok_or_else(|| missing(&key("row_dir")))?,
            )?;
            let not_ortho = |detail: String| RigError::NotOrthonormal {
                path: path.to_string(),
                index: k,
                face: name.clone(),
                detail,
            };
            if (col_dir.norm() - 1.0).abs() > ORTHONORMAL_TOLERANCE {
                return Err(not_ortho(format!("|col_dir| = {:.6}", col_dir.norm())));
            }
            if (row_dir.norm() - 1.0).abs() > ORTHONORMAL_TOLERANCE {
                return Err(not_ortho(format!("|row_dir| = {:.6}", row_dir.norm())));
            }
            if col_dir.dot(&row_dir).abs() > ORTHONORMAL_TOLERANCE {
                return Err(not_ortho(format!(
                    "col_dir · row_dir = {:.6}",
                    col_dir.dot(&row_dir)
                )));
            }
            let mut open_sides: Vec<FaceSide> = Vec::new();
            for (i, text) in rf.open_sides.iter().flatten().enumerate() {
                let Some(side) = FaceSide::ALL.into_iter().find(|s| s.as_str() == text) else {
                    return Err(invalid(
                        &key(&format!("open_sides[{i}]")),
                        "one of \"first_row\", \"last_row\", \"first_col\", \"last_col\"",
                        format!("{text:?}"),
                    ));
                };
                if open_sides.contains(&side) {
                    return Err(invalid(
                        &key(&format!("open_sides[{i}]")),
                        "each side at most once",
                        format!("{text:?} twice"),
                    ));
                }
                if open_sides.contains(&side.opposite()) {
                    return Err(invalid(
                        &key(&format!("open_sides[{i}]")),
                        "at most one of two opposite sides (the other fixes where the rows or columns start)",
                        format!("{text:?} and {:?}", side.opposite().as_str()),
                    ));
                }
                open_sides.push(side);
            }
            let charuco = match rf.charuco {
                None => None,
                Some(rc) => {
                    let ch = validate_charuco(path, k, rc, cols, rows, square_mm)?;
                    let natural = charuco::first_square(rows);
                    if let Some(fs) = rf.first_square
                        && fs != natural
                    {
                        return Err(invalid(
                            &key("first_square"),
                            "none on a ChArUco face (OpenCV's layout fixes the colours), or the colour it fixes",
                            format!("{fs:?} (OpenCV's layout makes it {natural:?})"),
                        ));
                    }
                    if !open_sides.is_empty() {
                        return Err(invalid(
                            &key("open_sides"),
                            "none on a ChArUco face (its markers name every square)",
                            format!("{} sides", open_sides.len()),
                        ));
                    }
                    Some(ch)
                }
            };
            let first_square = match &charuco {
                Some(_) => charuco::first_square(rows),
                None => rf.first_square.unwrap_or(SquareColour::Black),
            };
            // Exact Gram–Schmidt within the tolerance.
            let col_dir = col_dir.normalize();
            let row_dir = (row_dir - col_dir * col_dir.dot(&row_dir)).normalize();
            faces.push(Face {
                name,
                cols,
                rows,
                square_mm,
                margin_mm,
                origin,
                col_dir,
                row_dir,
                first_square,
                open_sides,
                charuco,
            });
        }
        for a in 0..faces.len() {
            for b in a + 1..faces.len() {
                if let Some(detail) = overlap(&faces[a], &faces[b]) {
                    return Err(RigError::FacesOverlap {
                        path: path.to_string(),
                        a: faces[a].name.clone(),
                        b: faces[b].name.clone(),
                        detail,
                    });
                }
            }
        }
        let mut seen: std::collections::HashMap<(usize, u32), &str> = Default::default();
        for (k, f) in faces.iter().enumerate() {
            let Some(ch) = &f.charuco else { continue };
            for &id in &ch.ids {
                if let Some(other) = seen.insert((ch.dictionary.bits, id), &f.name) {
                    return Err(invalid(
                        &format!("faces[{k}].charuco.ids"),
                        "marker ids used once in the rig (per marker size)",
                        format!("{id} (also on face '{other}')"),
                    ));
                }
            }
        }
        let up = match self.up {
            Some(v) => {
                let u = finite_vec("up", v)?;
                u.try_normalize(1e-12)
                    .ok_or_else(|| invalid("up", "a non-zero direction", fmt_vec(&v)))?
            }
            None => default_up(&faces),
        };
        let mut warnings = Vec::new();
        for f in &faces {
            if f.is_point_symmetric() && f.charuco.is_none() {
                warnings.push(RigWarning::SymmetricGrid {
                    face: f.name.clone(),
                    cols: f.cols,
                    rows: f.rows,
                });
            }
        }
        for a in 0..faces.len() {
            for b in a + 1..faces.len() {
                let (fa, fb) = (&faces[a], &faces[b]);
                // A face with open sides is never told apart by its size.
                let sized = fa.open_sides.is_empty()
                    && fb.open_sides.is_empty()
                    && fa.charuco.is_none()
                    && fb.charuco.is_none();
                if sized
                    && ((fa.cols, fa.rows) == (fb.cols, fb.rows)
                        || (fa.cols, fa.rows) == (fb.rows, fb.cols))
                {
                    warnings.push(RigWarning::SameGridSize {
                        a: fa.name.clone(),
                        b: fb.name.clone(),
                    });
                }
            }
        }
        Ok((
            Rig {
                name,
                up,
                body,
                faces,
            },
            warnings,
        ))
    }
}

/// Validate `faces[index].charuco` of a face of `cols × rows` inner corners.
fn validate_charuco(
    path: &str,
    index: usize,
    rc: RawCharuco,
    cols: usize,
    rows: usize,
    square_mm: f64,
) -> Result<charuco::Charuco, RigError> {
    let key = |field: &str| format!("faces[{index}].charuco.{field}");
    let missing = |field: &str| RigError::Missing {
        path: path.to_string(),
        key: key(field),
    };
    let invalid = |field: &str, expected: &str, value: String| RigError::Invalid {
        path: path.to_string(),
        key: key(field),
        expected: expected.to_string(),
        value,
    };
    let name = rc.dictionary.ok_or_else(|| missing("dictionary"))?;
    let dictionary = charuco::Dictionary::from_name(&name).ok_or_else(|| {
        invalid(
            "dictionary",
            "one of OpenCV's DICT_4X4_50 … DICT_6X6_1000",
            format!("{name:?}"),
        )
    })?;
    let marker_mm = rc.marker_mm.ok_or_else(|| missing("marker_mm"))?;
    if !(marker_mm > 0.0 && marker_mm < square_mm) {
        return Err(invalid(
            "marker_mm",
            &format!("a length in mm above 0 and below the square ({square_mm})"),
            marker_mm.to_string(),
        ));
    }
    let n = charuco::marker_count(cols, rows);
    let ids: Vec<i64> = match (rc.ids, rc.first_id) {
        (Some(_), Some(_)) => {
            return Err(invalid(
                "first_id",
                "either ids or first_id, not both",
                "both".into(),
            ));
        }
        (Some(ids), None) => ids,
        (None, first) => {
            let first = first.unwrap_or(0);
            (first..first + n as i64).collect()
        }
    };
    if ids.len() != n {
        return Err(invalid(
            "ids",
            &format!("{n} ids, one per white square of a {cols}×{rows} corner board"),
            format!("{} ids", ids.len()),
        ));
    }
    let mut out = Vec::with_capacity(n);
    for (i, &id) in ids.iter().enumerate() {
        let ok = u32::try_from(id)
            .ok()
            .filter(|&v| (v as usize) < dictionary.count);
        let Some(id) = ok else {
            return Err(invalid(
                &format!("ids[{i}]"),
                &format!(
                    "an id of {} (0 … {})",
                    dictionary.name(),
                    dictionary.count - 1
                ),
                id.to_string(),
            ));
        };
        if out.contains(&id) {
            return Err(invalid(
                &format!("ids[{i}]"),
                "ids used once",
                format!("{id} twice"),
            ));
        }
        out.push(id);
    }
    Ok(charuco::Charuco {
        dictionary,
        marker_mm,
        ids: out,
    })
}

/// `+z`, unless it is nearly along the mean face normal (a flat board lying in the xy plane), in
/// which case "up" on the first board: `−row_dir`.
fn default_up(faces: &[Face]) -> Vector3<f64> {
    let n: Vector3<f64> = faces.iter().map(Face::normal).sum();
    let n = n.try_normalize(1e-9).unwrap_or_else(Vector3::z);
    if n.z.abs() > 0.9 {
        faces.first().map(|f| -f.row_dir).unwrap_or_else(Vector3::y)
    } else {
        Vector3::z()
    }
}

/// Do the boards (with margins) of two faces overlap? Coplanar boards overlap when their rectangles
/// share area; other boards when each crosses the other's plane along a common segment. Touching
/// along an edge (within [`GEOMETRY_TOLERANCE_MM`]) is allowed.
fn overlap(fa: &Face, fb: &Face) -> Option<String> {
    let tol = GEOMETRY_TOLERANCE_MM;
    let na = fa.normal();
    let nb = fb.normal();
    let pa = fa.outline();
    let pb = fb.outline();
    let dist_b_to_a: Vec<f64> = pb.iter().map(|p| (p - fa.origin).dot(&na)).collect();
    let dist_a_to_b: Vec<f64> = pa.iter().map(|p| (p - fb.origin).dot(&nb)).collect();
    let parallel = na.cross(&nb).norm() < 1e-9;
    if parallel {
        if dist_b_to_a.iter().any(|d| d.abs() > tol) {
            return None; // parallel, different planes
        }
        // Coplanar: separating axis test of two rectangles in the plane, in face-a coordinates.
        let to2 =
            |f: &Face| -> Vec<(f64, f64)> { f.outline().iter().map(|p| fa.local(p)).collect() };
        let (qa, qb) = (to2(fa), to2(fb));
        let axes = [fa.col_dir, fa.row_dir, fb.col_dir, fb.row_dir]
            .map(|d| (d.dot(&fa.col_dir), d.dot(&fa.row_dir)));
        for (ax, ay) in axes {
            let proj = |q: &[(f64, f64)]| {
                q.iter()
                    .map(|(x, y)| x * ax + y * ay)
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                        (lo.min(v), hi.max(v))
                    })
            };
            let ((a0, a1), (b0, b1)) = (proj(&qa), proj(&qb));
            if a1 <= b0 + tol || b1 <= a0 + tol {
                return None;
            }
        }
        return Some("coplanar boards share area".into());
    }
    let crosses = |d: &[f64]| d.iter().any(|&x| x > tol) && d.iter().any(|&x| x < -tol);
    if !crosses(&dist_b_to_a) || !crosses(&dist_a_to_b) {
        return None;
    }
    // Both cross the other's plane: compare their segments on the common line.
    let dir = na.cross(&nb).normalize();
    let segment = |poly: &[Vector3<f64>; 4], d: &[f64]| -> (f64, f64) {
        let mut ts = Vec::new();
        for k in 0..4 {
            let (p, q) = (poly[k], poly[(k + 1) % 4]);
            let (dp, dq) = (d[k], d[(k + 1) % 4]);
            if (dp <= 0.0 && dq >= 0.0) || (dp >= 0.0 && dq <= 0.0) {
                let t = if (dp - dq).abs() < 1e-300 {
                    0.0
                } else {
                    dp / (dp - dq)
                };
                ts.push((p + (q - p) * t).dot(&dir));
            }
        }
        ts.iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            })
    };
    let (a0, a1) = segment(&pa, &dist_a_to_b);
    let (b0, b1) = segment(&pb, &dist_b_to_a);
    let common = a1.min(b1) - a0.max(b0);
    (common > tol).then(|| format!("the boards cross each other along {common:.3} mm"))
}
