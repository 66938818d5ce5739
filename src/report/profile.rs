//! Profile reports: one self-contained HTML page about a camera's stored profile — its identity, the
//! current version's intrinsics with σ, the QA verdict as stored, the lens distortion and projection
//! uncertainty from the stored covariance, and, when the store holds earlier versions, how each
//! parameter moved across them in σ units (a plot of all parameters and a table with the dates).
//!
//! ## What `PROFILE` names
//! As in `cubecal profile`, in this order (the first that exists wins):
//! 1. a profile document file (a run's `profile.json`, an exported history file); a store's
//!    `…/current.json` stands for its camera folder, so its history is included;
//! 2. a camera folder of a store (the folder holding `current.json` and `history/`);
//! 3. a camera identity (`usb:046d:0825:SERIAL`) or folder name in the store given by `--store`.
//!
//! ## σ units
//! Version `v` is placed at `(p_v − p_cur) / √(σ_v² + σ_cur²)` for every intrinsic `p` estimated in
//! both: the standard deviation of the difference of two independent estimates, exactly what
//! `cubecal profile diff CURRENT V` prints and what the store judges jumps with
//! ([`crate::profile::compare`]). The current version is therefore at 0 for every parameter, and a
//! point beyond the dashed `±k` lines is a version that differs from today's by more than the store's
//! jump threshold `k`. Parameters fixed (no σ) in a version have no point there.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use crate::profile::store::{CURRENT, HISTORY, Store, folder_name};
use crate::profile::{CommitOptions, Profile, compare, display_identity, read_document};

use super::plots::{HistoryFigure, Series};
use super::{
    PARAM_ORDER, Plot, ReportError, banner, esc, fit_summary, fmt_num, kv_rows, lens_plots,
    page_start, parameter_table, plot, plots_section, png_dir_name, verdict_table, write_outputs,
};

/// One stored version of a profile.
#[derive(Debug, Clone)]
pub struct Version {
    /// The document it was read from.
    pub path: PathBuf,
    pub profile: Profile,
}

/// Everything a profile report is made from.
#[derive(Debug, Clone)]
pub struct ProfileData {
    /// What was reported on, as the report names it (a file or a camera folder).
    pub source: PathBuf,
    /// The current profile, the one the report is about.
    pub current: Version,
    /// Earlier versions, oldest first.
    pub history: Vec<Version>,
    /// History documents that could not be used, and why (they are listed in the report).
    pub skipped: Vec<(PathBuf, String)>,
}

impl ProfileData {
    /// The profile the report is about (the newest version).
    pub fn current(&self) -> &Profile {
        &self.current.profile
    }

    /// Every version, oldest first (the current one last).
    pub fn versions(&self) -> Vec<&Version> {
        self.history
            .iter()
            .chain(std::iter::once(&self.current))
            .collect()
    }

    /// A single profile document, without history.
    pub fn from_file(path: &Path) -> Result<ProfileData, ReportError> {
        let profile = read_document(path)?;
        Ok(ProfileData {
            source: path.to_path_buf(),
            current: Version {
                path: path.to_path_buf(),
                profile,
            },
            history: Vec::new(),
            skipped: Vec::new(),
        })
    }

    /// A camera folder of a store: `current.json` and every version in `history/`.
    pub fn from_folder(folder: &Path) -> Result<ProfileData, ReportError> {
        let folder = std::path::absolute(folder).map_err(|source| ReportError::Read {
            path: folder.to_path_buf(),
            source,
        })?;
        let (Some(root), Some(name)) = (folder.parent(), folder.file_name()) else {
            return Err(ReportError::NothingToReport {
                target: folder.display().to_string(),
                store: folder.clone(),
            });
        };
        let store = Store::open(root)?;
        Self::from_store(&store, &name.to_string_lossy())
    }

    /// The camera `device` (identity or folder name) of `store`, with its history.
    pub fn from_store(store: &Store, device: &str) -> Result<ProfileData, ReportError> {
        let folder = store.resolve(device)?;
        let (current, _) = store.current(device)?;
        let mut history = Vec::new();
        let mut skipped = Vec::new();
        for path in store.history(device)? {
            match read_document(&path) {
                Ok(p) if p.identity.id == current.identity.id => {
                    history.push(Version { path, profile: p })
                }
                Ok(p) => skipped.push((
                    path,
                    format!(
                        "holds the profile of '{}', not of this camera",
                        display_identity(&p.identity.id)
                    ),
                )),
                Err(e) => skipped.push((path, e.to_string())),
            }
        }
        Ok(ProfileData {
            current: Version {
                path: folder.join(CURRENT),
                profile: current,
            },
            source: folder,
            history,
            skipped,
        })
    }

    /// The profile of `device` and its history as any store keeps them (a PostgreSQL store too): the
    /// versions are named by where they are stored.
    pub fn from_backend(
        store: &dyn crate::profile::ProfileStore,
        device: &str,
    ) -> Result<ProfileData, ReportError> {
        let (current, _) = store.current_profile(device)?;
        let mut history = Vec::new();
        let mut skipped = Vec::new();
        for (place, doc) in store.earlier_profiles(device)? {
            let place = PathBuf::from(place);
            match doc {
                Ok(p) if p.identity.id == current.identity.id => history.push(Version {
                    path: place,
                    profile: p,
                }),
                Ok(p) => skipped.push((
                    place,
                    format!(
                        "holds the profile of '{}', not of this camera",
                        display_identity(&p.identity.id)
                    ),
                )),
                Err(e) => skipped.push((place, e.to_string())),
            }
        }
        let source = PathBuf::from(format!(
            "{} / {}",
            store.describe(),
            display_identity(&current.identity.id)
        ));
        Ok(ProfileData {
            current: Version {
                path: source.clone(),
                profile: current,
            },
            source,
            history,
            skipped,
        })
    }

    /// What `cubecal report PROFILE` names (see the module docs); `store_dir` is `--store`. A store
    /// directory that does not exist is not created.
    pub fn locate(target: &str, store_dir: &Path) -> Result<ProfileData, ReportError> {
        let path = Path::new(target);
        if path.is_file() {
            let in_store_folder = path.file_name().is_some_and(|n| n == CURRENT)
                && path.parent().is_some_and(|d| d.join(HISTORY).is_dir());
            return match path.parent() {
                Some(folder) if in_store_folder => Self::from_folder(folder),
                _ => Self::from_file(path),
            };
        }
        if path.is_dir() && path.join(CURRENT).is_file() {
            return Self::from_folder(path);
        }
        let nothing = || ReportError::NothingToReport {
            target: target.to_string(),
            store: store_dir.to_path_buf(),
        };
        if !store_dir.is_dir() {
            return Err(nothing());
        }
        let store = Store::open(store_dir)?;
        match Self::from_store(&store, target) {
            Err(ReportError::Profile(crate::profile::ProfileError::NotFound { .. })) => {
                Err(nothing())
            }
            other => other,
        }
    }

    /// The default report file: `report-<camera folder name>.html` in the current directory (the
    /// store itself belongs to the station service and is not written into).
    pub fn default_out(&self) -> PathBuf {
        PathBuf::from(format!(
            "report-{}.html",
            folder_name(&self.current().identity.id)
        ))
    }

    /// The store's jump threshold the current profile was judged with (the default when it is the
    /// camera's first profile).
    pub fn jump_sigma(&self) -> f64 {
        self.current()
            .change
            .as_ref()
            .map_or(CommitOptions::default().jump_sigma, |c| c.jump_sigma)
    }
}

/// Each parameter's offset from the current version in σ units, per version (oldest first): see the
/// module docs. Parameters appear in table order when at least one version has a value.
pub fn history_series(versions: &[&Profile], jump_sigma: f64) -> Vec<Series> {
    let Some(current) = versions.last() else {
        return Vec::new();
    };
    // compare(current → v): delta = p_v − p_cur, sigma = √(σ_cur² + σ_v²).
    let changes: Vec<_> = versions
        .iter()
        .map(|v| compare(current, "", v, jump_sigma))
        .collect();
    PARAM_ORDER
        .iter()
        .map(|&name| {
            let values: Vec<Option<f64>> = changes
                .iter()
                .map(|c| {
                    c.params
                        .iter()
                        .find(|p| p.name == name && p.fixed.is_none())
                        .map(|p| p.delta_sigma)
                })
                .collect();
            (name.to_string(), values)
        })
        .filter(|(_, v)| v.iter().any(Option::is_some))
        .collect()
}

/// A rendered profile report.
#[derive(Debug, Clone)]
pub struct ProfileReport {
    pub html: String,
    pub plots: Vec<Plot>,
    /// The plotted history (empty for a profile without earlier versions).
    pub series: Vec<Series>,
}

/// Render the report of a loaded profile. `png_dir` is the relative folder the PNG links point to.
pub fn render_profile(data: &ProfileData, png_dir: &str) -> Result<ProfileReport, ReportError> {
    let current = data.current();
    let cal = &current.calibration;
    let path = &data.current.path;
    let cam = super::analysis::camera_from_report(cal).map_err(|source| ReportError::Camera {
        path: path.clone(),
        source,
    })?;
    let (mut plots, mut notes) = lens_plots(cal, &cam)?;
    let profiles: Vec<&Profile> = data.versions().iter().map(|v| &v.profile).collect();
    let jump_sigma = data.jump_sigma();
    let series = if profiles.len() >= 2 {
        history_series(&profiles, jump_sigma)
    } else {
        Vec::new()
    };
    if profiles.len() >= 2 {
        let n = profiles.len();
        plots.push(plot(
            &HistoryFigure {
                caption: format!(
                    "Each version's distance from the current one (v{n}) in σ of the difference"
                ),
                versions: profiles.iter().map(|p| version_date(&p.created)).collect(),
                series: series.clone(),
                jump_sigma,
            },
            format!(
                "Per version and intrinsic parameter: (p_v − p_current) / √(σ_v² + σ_current²), as \
                 `cubecal profile diff` prints it. The current version v{n} is 0 by definition; a \
                 version outside the dashed ±{jump_sigma} σ lines differs from today's calibration by \
                 more than the store's jump threshold. A steady slope is a drift; one version apart \
                 from the rest is a jump (a bumped lens, or another camera)."
            ),
        )?);
    } else {
        notes.push(
            "No earlier version of this profile (no history in the store, or a single profile file \
             was given): nothing to compare it with."
                .to_string(),
        );
    }
    for (p, why) in &data.skipped {
        notes.push(format!(
            "History file {} left out: {why}",
            p.display().to_string().escape_debug()
        ));
    }
    let html = html(data, &plots, &series, &notes, png_dir);
    Ok(ProfileReport {
        html,
        plots,
        series,
    })
}

/// `2026-11-25T15:04:05.25Z` → `2026-11-25 15:04:05` (the label of a version).
fn version_date(created: &str) -> String {
    let shown: String = created.chars().take(19).collect();
    display_identity(&shown.replacen('T', " ", 1))
}

fn html(
    data: &ProfileData,
    plots: &[Plot],
    series: &[Series],
    notes: &[String],
    png_dir: &str,
) -> String {
    let p = data.current();
    let cal = &p.calibration;
    let mut h = page_start("cubecal profile report");
    let _ = writeln!(
        h,
        "<p>Camera <code>{}</code>; profile of {} read from <code>{}</code>; {} version(s).</p>",
        esc(&display_identity(&p.identity.id)),
        esc(&display_identity(&p.created)),
        esc(&data.source.display().to_string().escape_debug().to_string()),
        data.history.len() + 1
    );
    h.push_str(&banner(p.verdict.pass));

    h.push_str("<h2>Device</h2>\n<table>");
    let origin = serde_json::to_value(p.identity.origin).unwrap_or_default();
    let mut rows = vec![
        ("identity".to_string(), display_identity(&p.identity.id)),
        (
            "identity from".to_string(),
            origin.as_str().unwrap_or("").to_string(),
        ),
        (
            "rig".to_string(),
            format!("{} (sha256 {})", p.rig.name, p.rig.sha256),
        ),
        ("created".to_string(), p.created.clone()),
        (
            "software".to_string(),
            format!("cubecal {}", p.software_version),
        ),
    ];
    if let Some(s) = &p.session {
        rows.push((
            "session".to_string(),
            format!(
                "{} (manifest sha256 {})",
                s.path.display(),
                s.manifest_sha256
            ),
        ));
    }
    for (k, v) in rows {
        let _ = write!(
            h,
            "<tr><th>{}</th><td>{}</td></tr>",
            esc(&k),
            esc(&display_identity(&v))
        );
    }
    if let Some(d) = &p.identity.device {
        h.push_str(&kv_rows(&serde_json::to_value(d).unwrap_or_default()));
    }
    if let Some(f) = &p.format {
        let _ = write!(
            h,
            "<tr><th>format</th><td>{}</td></tr>",
            esc(&serde_json::to_string(f).unwrap_or_default())
        );
    }
    for c in &p.controls {
        let _ = write!(
            h,
            "<tr><th>control</th><td>{}</td></tr>",
            esc(&serde_json::to_string(c).unwrap_or_default())
        );
    }
    h.push_str("</table>\n");

    h.push_str(&verdict_table(&p.verdict));
    h.push_str(&parameter_table(cal));
    let _ = writeln!(
        h,
        "<p>Image {}×{}; {}.</p>",
        cal.image_size[0],
        cal.image_size[1],
        fit_summary(cal)
    );
    if let Some(c) = &p.change {
        let _ = writeln!(
            h,
            "<p>Stored change from the previous profile ({}): largest |Δ/σ| {} against the \
             threshold {}: <span class=\"{}\">{}</span>.</p>",
            esc(&display_identity(&c.previous_created)),
            fmt_num(c.max_abs_delta_sigma),
            fmt_num(c.jump_sigma),
            if c.jump { "fail" } else { "pass" },
            if c.jump { "JUMP" } else { "within threshold" }
        );
    }
    for n in notes {
        let _ = writeln!(h, "<p class=\"note\">{}</p>", esc(n));
    }
    h.push_str(&plots_section(plots, png_dir));
    if !series.is_empty() {
        h.push_str(&history_table(data, series));
    }
    h.push_str("</body></html>\n");
    h
}

/// One row per version (oldest first): date, file, verdict, RMS, the stored step change, and per
/// parameter the value with its offset from the current version in σ (the plotted number).
fn history_table(data: &ProfileData, series: &[Series]) -> String {
    let mut h = String::from(
        "<h2>History</h2>\n<p>Each cell: the parameter's value, and below it the version's distance \
         from the current one in σ (the plotted number; empty where the parameter was not \
         estimated). “Step” is the change from the version before, as the store recorded it. Hover a \
         version for its file.</p>\n\
         <table class=\"hist\"><tr><th>version</th><th>created</th><th>verdict</th><th>RMS (px)</th>\
         <th>step max |Δ/σ|</th>",
    );
    for (name, _) in series {
        let _ = write!(h, "<th>{}</th>", esc(name));
    }
    h.push_str("</tr>\n");
    for (i, v) in data.versions().iter().enumerate() {
        let p = &v.profile;
        let values = crate::profile::intrinsic_values(&p.calibration);
        let step = match &p.change {
            Some(c) => format!(
                "{}{}",
                fmt_num(c.max_abs_delta_sigma),
                if c.jump {
                    " <span class=\"fail\">JUMP</span>"
                } else {
                    ""
                }
            ),
            None => String::from("first"),
        };
        let _ = write!(
            h,
            "<tr><td title=\"{}\">v{}</td><td>{}</td><td class=\"{}\">{}</td><td class=\"num\">{}</td>\
             <td class=\"num\">{}</td>",
            esc(&v.path.display().to_string().escape_debug().to_string()),
            i + 1,
            esc(&version_date(&p.created)),
            if p.verdict.pass { "pass" } else { "fail" },
            if p.verdict.pass { "pass" } else { "FAIL" },
            fmt_num(p.calibration.rms_px),
            step
        );
        for (name, z) in series {
            let value = values
                .get(name.as_str())
                .map_or(String::new(), |x| fmt_num(*x));
            let z = z[i].map_or(String::new(), |z| format!("{z:+.2} σ"));
            let _ = write!(h, "<td class=\"num\">{value}<br><small>{z}</small></td>");
        }
        h.push_str("</tr>\n");
    }
    h.push_str("</table>\n");
    h
}

/// Write the report of a loaded profile to `out` and its plots as PNG into `<out stem>_plots/`
/// beside it. Returns the HTML path.
pub fn write_profile_report(data: &ProfileData, out: &Path) -> Result<PathBuf, ReportError> {
    let png_dir = png_dir_name(out);
    let report = render_profile(data, &png_dir)?;
    write_outputs(out, &report.html, &report.plots, &png_dir)?;
    tracing::info!(path = %out.display(), plots = report.plots.len(), versions = data.history.len() + 1, "wrote profile report");
    Ok(out.to_path_buf())
}
