//! ChArUco faces: OpenCV's predefined ArUco dictionaries and where a ChArUco board prints its markers.
//!
//! ## Dictionaries
//! The 4×4, 5×5 and 6×6 predefined dictionaries of OpenCV (`DICT_4X4_50` … `DICT_6X6_1000`), bit for
//! bit: `data/aruco_dictionaries.txt` is written from `cv2.aruco` by `scripts/aruco_dictionaries.py`
//! (provenance and format in the script) and `tests/charuco_opencv.rs` compares every marker with the
//! installed cv2. The `_50/_100/_250` dictionaries are the first ids of the `_1000` one (checked by
//! the script) and differ only in how many bit errors OpenCV corrects (`maxCorrectionBits`).
//!
//! Crates looked at: `aruco-rs` 0.1 (a port of the JavaScript ARuco-ts, one release, its own
//! dictionary set and a WASM focus), `calib-targets-aruco` (dictionaries and decoding of cells a grid
//! already located, no quad detection; young), the `opencv` bindings (need a system OpenCV, a heavy
//! build dependency for a station). None gives OpenCV's dictionaries with a marker detector suited to
//! ours, so the tables come from OpenCV itself and the decoding is ours ([`crate::detect::charuco`]).
//!
//! ## Board layout (OpenCV's `CharucoBoard`, OpenCV ≥ 4.6, not the legacy pattern)
//! A face of `cols × rows` inner corners is a board of `(cols + 1) × (rows + 1)` squares. OpenCV
//! numbers squares `(X, Y)` from the top left of the board as printed (x right, y down); square
//! `(0, 0)` is black, and every white square holds a marker centred in it, `marker_mm` wide, whose ids
//! are taken in order of the white squares row by row from the top (`ids`). OpenCV's ChArUco corner
//! `k = y·cols + x` is the inner corner at `((x + 1)·s, (y + 1)·s)`.
//!
//! cubecal's faces are seen from the front with columns to the right and rows *up* (see
//! [`super::svg`]), so OpenCV's corner `(x, y)` is cubecal's `(row, col) = (rows − 1 − y, x)`, and
//! OpenCV's square `(X, Y)` is cubecal's square `(i, j) = (rows − Y, X)`; the colour of cubecal's
//! square `(0, 0)` follows (black when `rows` is even).

use std::sync::OnceLock;

use super::SquareColour;

/// One of OpenCV's predefined 4×4, 5×5 and 6×6 ArUco dictionaries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Dictionary {
    /// Bits along a side of a marker's data (4, 5 or 6); a marker is that plus a black border cell.
    pub bits: usize,
    /// Number of markers (50, 100, 250 or 1000).
    pub count: usize,
}

/// The names of the predefined dictionaries, as in OpenCV.
pub const DICTIONARY_NAMES: [&str; 12] = [
    "DICT_4X4_50",
    "DICT_4X4_100",
    "DICT_4X4_250",
    "DICT_4X4_1000",
    "DICT_5X5_50",
    "DICT_5X5_100",
    "DICT_5X5_250",
    "DICT_5X5_1000",
    "DICT_6X6_50",
    "DICT_6X6_100",
    "DICT_6X6_250",
    "DICT_6X6_1000",
];

/// The tables as parsed from `data/aruco_dictionaries.txt`: per size, the codes of the 1000 markers
/// and the maximum correction bits of the 50/100/250/1000 dictionaries.
#[derive(Debug)]
struct Tables {
    codes: [Vec<u64>; 3],
    corrections: [[u32; 4]; 3],
}

const COUNTS: [usize; 4] = [50, 100, 250, 1000];

fn tables() -> &'static Tables {
    static TABLES: OnceLock<Tables> = OnceLock::new();
    TABLES.get_or_init(|| {
        let text = include_str!("../../data/aruco_dictionaries.txt");
        let mut t = Tables {
            codes: Default::default(),
            corrections: [[0; 4]; 3],
        };
        let mut current: Option<usize> = None;
        for line in text.lines() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            if let Some(rest) = line.strip_prefix("dictionary ") {
                let mut parts = rest.split_whitespace();
                let n: usize = parts.next().and_then(|p| p.parse().ok()).unwrap_or(0);
                current = (4..=6).contains(&n).then_some(n - 4);
                if let Some(k) = current {
                    for (slot, part) in parts.enumerate().take(4) {
                        t.corrections[k][slot] = part
                            .split_once(':')
                            .and_then(|(_, c)| c.parse().ok())
                            .unwrap_or(0);
                    }
                }
            } else if let (Some(k), Ok(code)) = (current, u64::from_str_radix(line, 16)) {
                t.codes[k].push(code);
            }
        }
        t
    })
}

impl Dictionary {
    /// The dictionary of an OpenCV name such as `DICT_6X6_1000`.
    pub fn from_name(name: &str) -> Option<Dictionary> {
        let rest = name.strip_prefix("DICT_")?;
        let (size, count) = rest.split_once('_')?;
        let bits = match size {
            "4X4" => 4,
            "5X5" => 5,
            "6X6" => 6,
            _ => return None,
        };
        let count: usize = count.parse().ok()?;
        COUNTS
            .contains(&count)
            .then_some(Dictionary { bits, count })
    }

    /// OpenCV's name.
    pub fn name(&self) -> String {
        format!("DICT_{0}X{0}_{1}", self.bits, self.count)
    }

    /// Marker `id`'s data bits in rotation 0 (as printed), row-major from the top-left bit, the
    /// first bit the most significant of the `bits²`; a 1 is a white cell. `None` past the end.
    pub fn code(&self, id: u32) -> Option<u64> {
        let id = id as usize;
        if id >= self.count {
            return None;
        }
        tables().codes[self.bits - 4].get(id).copied()
    }

    /// The codes of every marker of the dictionary, by id.
    pub fn codes(&self) -> &'static [u64] {
        let all = &tables().codes[self.bits - 4];
        &all[..self.count.min(all.len())]
    }

    /// How many wrong bits OpenCV's dictionary says can be corrected (`maxCorrectionBits`).
    pub fn max_correction_bits(&self) -> u32 {
        let slot = COUNTS.iter().position(|&c| c == self.count).unwrap_or(0);
        tables().corrections[self.bits - 4][slot]
    }

    /// Whether cell `(r, c)` of marker `id`'s data (row from the top as printed) is white.
    pub fn bit(&self, code: u64, r: usize, c: usize) -> bool {
        let n = self.bits;
        (code >> (n * n - 1 - (r * n + c))) & 1 == 1
    }
}

/// Rotate a code by 90° clockwise as seen: the printed cell `(r, c)` moves to `(c, n − 1 − r)`.
pub fn rotate_code(code: u64, n: usize) -> u64 {
    let mut out = 0u64;
    for r in 0..n {
        for c in 0..n {
            let bit = (code >> (n * n - 1 - (r * n + c))) & 1;
            let (r2, c2) = (c, n - 1 - r);
            out |= bit << (n * n - 1 - (r2 * n + c2));
        }
    }
    out
}

/// The ChArUco part of a face: which dictionary, how large the markers are, and their ids.
#[derive(Debug, Clone, PartialEq)]
pub struct Charuco {
    pub dictionary: Dictionary,
    /// Side of a marker (its black border included), mm; less than the square.
    pub marker_mm: f64,
    /// Marker ids in OpenCV's order: white squares row by row from the top of the printed board.
    pub ids: Vec<u32>,
}

/// Number of white squares (markers) of a ChArUco board of `cols × rows` inner corners.
pub fn marker_count(cols: usize, rows: usize) -> usize {
    let (sx, sy) = (cols + 1, rows + 1);
    (sx * sy) / 2
}

/// Colour of cubecal's square `(0, 0)` on a ChArUco face of `rows` inner corner rows.
pub fn first_square(rows: usize) -> SquareColour {
    if rows.is_multiple_of(2) {
        SquareColour::Black
    } else {
        SquareColour::White
    }
}

/// OpenCV's square `(X, Y)` of cubecal's square `(i, j)` on a face of `rows` inner corner rows.
pub fn opencv_square(rows: usize, i: usize, j: usize) -> (usize, usize) {
    (j, rows - i)
}

/// OpenCV's ChArUco corner id of cubecal's inner corner `(row, col)`.
pub fn opencv_corner_id(cols: usize, rows: usize, row: usize, col: usize) -> usize {
    (rows - 1 - row) * cols + col
}

impl Charuco {
    /// Index into `ids` of the marker in OpenCV's square `(x, y)` of a board of `cols` inner corner
    /// columns, `None` for a black square.
    pub fn marker_index(cols: usize, x: usize, y: usize) -> Option<usize> {
        let sx = cols + 1;
        if (x + y).is_multiple_of(2) {
            return None;
        }
        let before_rows = (y / 2) * sx + (y % 2) * (sx / 2);
        let in_row = if y.is_multiple_of(2) {
            x / 2
        } else {
            x.div_ceil(2)
        };
        Some(before_rows + in_row)
    }

    /// Whether OpenCV-board point `(x, y)` (mm from the board's top-left square corner, y down) in
    /// the white square `(sq_x, sq_y)` holding marker `id` is black: on the marker's border or a 0 bit.
    pub fn marker_ink(
        &self,
        square_mm: f64,
        sq_x: usize,
        sq_y: usize,
        id: u32,
        x: f64,
        y: f64,
    ) -> bool {
        let n = self.dictionary.bits;
        let d = (square_mm - self.marker_mm) / 2.0;
        let u = (x - sq_x as f64 * square_mm - d) / self.marker_mm;
        let v = (y - sq_y as f64 * square_mm - d) / self.marker_mm;
        if !(0.0..1.0).contains(&u) || !(0.0..1.0).contains(&v) {
            return false;
        }
        let cells = (n + 2) as f64;
        let (c, r) = ((u * cells) as usize, (v * cells) as usize);
        if r == 0 || c == 0 || r == n + 1 || c == n + 1 {
            return true;
        }
        match self.dictionary.code(id) {
            Some(code) => !self.dictionary.bit(code, r - 1, c - 1),
            None => false,
        }
    }
}
