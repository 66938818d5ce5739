//! Opening what a station run needs from its configuration: the frame source and the turntable,
//! including the built-in protocol simulators on a pseudo-terminal and the synthetic camera that
//! renders the rig at the angle the turntable reports.

use std::path::PathBuf;
use std::time::Duration;

use super::StationError;
use super::config::{PlannerKind, SourceKind, StationConfig, TurntableKind};
use super::plan::StagePose;
use crate::capture::images::ImageFiles;
use crate::capture::session::{ReplaySource, Session};
use crate::capture::synthetic::{AngleCell, SyntheticSource, TurntableScene};
use crate::capture::v4l2::{
    ControlSetting, DeviceInfo, LockSettings, Negotiated, V4l2Config, V4l2Source,
};
use crate::capture::{FrameSource, convert::PixelFormat};
use crate::render::{default_view, random_poses};
use crate::rig::Rig;
use crate::turntable::Turntable;
use crate::turntable::grbl::{Axis, GrblConfig, GrblTurntable};
use crate::turntable::manual::{FixedRig, MANUAL_RESOLUTION, ManualTurntable, Operator};
use crate::turntable::sim::{self, GrblSim, SimConfig, SimHandle, ZaberSim};
use crate::turntable::zaber::{ZaberConfig, ZaberTurntable};
use serialport::SerialPort;

/// Baud rate of both serial protocols.
pub const BAUD: u32 = 115_200;

/// How the poses of a run are made.
#[derive(Debug, Clone, PartialEq)]
pub enum Poses {
    /// Turntable angles (degrees), moved to one after the other.
    Angles(Vec<f64>),
    /// A two-axis stage (rotation and tilt): at most `poses` poses, chosen one by one by the
    /// planner ([`crate::station::plan`]), or `sweep` in order.
    Stage {
        poses: usize,
        sweep: Option<Vec<StagePose>>,
    },
    /// A sequence of frames that arrive by themselves (replayed session, photos, a person moving
    /// the camera in front of a fixed rig): `n` poses of `frames_per_pose` frames, with the angle
    /// recorded for each pose when known.
    Frames { angles: Vec<Option<f64>> },
}

impl Poses {
    /// The number of poses planned (the most a planned stage run takes).
    pub fn len(&self) -> usize {
        match self {
            Poses::Angles(a) => a.len(),
            Poses::Stage { poses, sweep } => sweep.as_ref().map_or(*poses, |s| s.len().min(*poses)),
            Poses::Frames { angles } => angles.len(),
        }
    }

    /// Whether no pose is planned.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The poses of a moving stage: one-axis angles, or the two-axis plan (`plan.planner`).
fn stage_poses(cfg: &StationConfig, tilt: Option<(f64, f64)>) -> Poses {
    let p = &cfg.plan;
    match tilt {
        None => Poses::Angles(plan_angles(p.poses, p.sweep_deg)),
        Some(limits) => Poses::Stage {
            poses: p.poses,
            sweep: (p.planner == PlannerKind::Sweep)
                .then(|| crate::station::plan::grid(p.sweep_deg, Some(limits), p.step_deg)),
        },
    }
}

/// Everything a run drives.
pub struct Hardware {
    pub source: Box<dyn FrameSource>,
    pub turntable: Box<dyn Turntable>,
    /// What to tell about the turntable.
    pub turntable_name: String,
    pub poses: Poses,
    /// Set after every settled move, for a synthetic camera to render at.
    pub angle: Option<AngleCell>,
    /// Set after every settled tilt (two-axis stages).
    pub tilt: Option<AngleCell>,
    /// Keeps the protocol simulators alive for the run.
    pub simulator: Vec<SimHandle>,
    pub device: Option<DeviceInfo>,
    pub capture: Option<Negotiated>,
    pub controls: Vec<ControlSetting>,
    /// The identity profiles are stored under.
    pub identity: Option<String>,
    /// The replayed session, when replaying.
    pub replayed: Option<PathBuf>,
}

impl std::fmt::Debug for Hardware {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Hardware")
            .field("source", &self.source.describe())
            .field("turntable", &self.turntable_name)
            .field("poses", &self.poses)
            .finish()
    }
}

/// Turntable angles of a plan: `n` equal steps over `sweep_deg`, centred on 0°.
pub fn plan_angles(n: usize, sweep_deg: f64) -> Vec<f64> {
    let step = sweep_deg / n.max(1) as f64;
    (0..n)
        .map(|k| (k as f64 - (n as f64 - 1.0) / 2.0) * step)
        .collect()
}

/// Fast simulator motion (the station waits for moves like on hardware, only shorter).
fn sim_motion(units_per_degree: f64) -> SimConfig {
    SimConfig {
        speed: 2000.0 * units_per_degree,
        accel: 20000.0 * units_per_degree,
        fault: None,
    }
}

/// One axis's driver, the simulator serving it (if any) and its description.
type OneAxis = (Box<dyn Turntable>, Option<SimHandle>, String);

/// A turntable, the simulators serving it (if any) and its description.
pub type OpenedTurntable = (Box<dyn Turntable>, Vec<SimHandle>, String);

/// Open the turntable the config names, on a tilting cradle when it has one
/// ([`TurntableSection::has_tilt`](super::config::TurntableSection::has_tilt)) and the kind can
/// have one (the simulators always; GRBL and Zaber with `turntable.tilt_port`): the tilt
/// driver is a second simulator of the same protocol (GRBL on axis B, Zaber device 2) or the driver
/// on `tilt_port`. `operator` answers a manual turntable's prompts.
pub fn open_turntable(
    cfg: &StationConfig,
    operator: Option<Box<dyn Operator>>,
) -> Result<OpenedTurntable, StationError> {
    let t = &cfg.turntable;
    let (rotation, sim, name) = open_axis(cfg, operator, t.port.clone(), Axis::A, 1)?;
    let tilt_port = match t.kind {
        TurntableKind::SimGrbl | TurntableKind::SimZaber => Some(None),
        TurntableKind::Grbl | TurntableKind::Zaber => t.tilt_port.clone().map(Some),
        TurntableKind::Manual | TurntableKind::None => None,
    };
    let Some(port) = tilt_port.filter(|_| t.has_tilt()) else {
        return Ok((rotation, sim.into_iter().collect(), name));
    };
    let (tilt, tilt_sim, tilt_name) = open_axis(cfg, None, port, Axis::B, 2)?;
    let stage = crate::turntable::stage::TiltStage::new(
        rotation,
        tilt,
        (
            crate::turntable::Degrees(t.tilt_min_deg),
            crate::turntable::Degrees(t.tilt_max_deg),
        ),
    )?;
    let mut sims: Vec<SimHandle> = Vec::new();
    sims.extend(sim);
    sims.extend(tilt_sim);
    Ok((
        Box::new(stage),
        sims,
        format!(
            "{name}, tilting [{}°, {}°] on {tilt_name}",
            t.tilt_min_deg, t.tilt_max_deg
        ),
    ))
}

/// One axis: the driver of `cfg.turntable.kind` on `port` (simulators: a new one, on `axis` /
/// Zaber `device`).
fn open_axis(
    cfg: &StationConfig,
    operator: Option<Box<dyn Operator>>,
    port: Option<String>,
    axis: Axis,
    device: u8,
) -> Result<OneAxis, StationError> {
    let t = &cfg.turntable;
    let move_timeout = Duration::from_secs(t.move_timeout_s);
    let exchange_timeout = Duration::from_millis(t.reply_timeout_ms);
    let grbl_config = GrblConfig {
        exchange_timeout,
        move_timeout,
        home_timeout: move_timeout * 2,
        ..GrblConfig::new(axis, t.degrees_per_unit)
    };
    // The simulators' tilt is device 2 (a daisy-chained second device); hardware on its own port
    // answers as device 1.
    let zaber_device = if t.kind == TurntableKind::SimZaber {
        device
    } else {
        1
    };
    let zaber_config = ZaberConfig {
        device: zaber_device,
        exchange_timeout,
        move_timeout,
        home_timeout: move_timeout * 2,
        ..ZaberConfig::new(t.microsteps_per_degree)
    };
    let port_path = || port.clone().unwrap_or_default();
    Ok(match t.kind {
        TurntableKind::None => (Box::new(FixedRig), None, "none (fixed rig)".into()),
        TurntableKind::Manual => {
            let op = operator.ok_or_else(|| StationError::NoOperator)?;
            let table = ManualTurntable::new(op, MANUAL_RESOLUTION)?;
            if t.has_tilt() {
                let limits = (
                    crate::turntable::Degrees(t.tilt_min_deg),
                    crate::turntable::Degrees(t.tilt_max_deg),
                );
                (
                    Box::new(table.with_tilt(limits)),
                    None,
                    "manual with a tilting cradle (operator prompts)".into(),
                )
            } else {
                (Box::new(table), None, "manual (operator prompts)".into())
            }
        }
        TurntableKind::Grbl => {
            let port = crate::turntable::serial::open_port(&port_path(), BAUD)?;
            (
                Box::new(GrblTurntable::new(port, grbl_config)?),
                None,
                format!("GRBL on {}", port_path()),
            )
        }
        TurntableKind::Zaber => {
            let port = crate::turntable::serial::open_port(&port_path(), BAUD)?;
            (
                Box::new(ZaberTurntable::new(port, zaber_config)?),
                None,
                format!("Zaber on {}", port_path()),
            )
        }
        TurntableKind::SimGrbl => {
            let (port, handle) = sim::grbl_pair(
                sim_motion(1.0 / t.degrees_per_unit.abs()),
                GrblSim {
                    axis,
                    homing: false,
                },
            )?;
            let name = format!(
                "GRBL simulator on {}",
                port.name().unwrap_or_else(|| "a pseudo-terminal".into())
            );
            (
                Box::new(GrblTurntable::new(port, grbl_config)?),
                Some(handle),
                name,
            )
        }
        TurntableKind::SimZaber => {
            let (port, handle) = sim::zaber_pair(
                sim_motion(t.microsteps_per_degree),
                ZaberSim {
                    device,
                    limit_microsteps: (crate::turntable::MAX_ABS_DEGREES * t.microsteps_per_degree)
                        as i64,
                },
            )?;
            let name = format!(
                "Zaber simulator on {}",
                port.name().unwrap_or_else(|| "a pseudo-terminal".into())
            );
            (
                Box::new(ZaberTurntable::new(port, zaber_config)?),
                Some(handle),
                name,
            )
        }
    })
}

/// Open the camera and turntable of `cfg` for rig `rig`.
pub fn open(
    cfg: &StationConfig,
    rig: &Rig,
    operator: Option<Box<dyn Operator>>,
) -> Result<Hardware, StationError> {
    let c = &cfg.camera;
    let n = cfg.plan.poses;
    match c.source {
        SourceKind::Replay => {
            let dir = c.replay.clone().unwrap_or_default();
            let src = ReplaySource::open(&dir)?;
            let session: &Session = src.session();
            if session.manifest.incomplete() {
                tracing::warn!(
                    "{}: this session was recorded incomplete ({}); the replay has only the poses captured before that",
                    dir.display(),
                    session
                        .manifest
                        .ended_by
                        .as_deref()
                        .or_else(|| session.manifest.header.config.get("ended_by")?.as_str())
                        .unwrap_or("ended early")
                );
            }
            let fpp = cfg.camera.frames_per_pose.max(1) as usize;
            let angles: Vec<Option<f64>> = session
                .manifest
                .frames
                .chunks(fpp)
                .map(|ch| ch.first().and_then(|f| f.angle_deg))
                .collect();
            let header = session.manifest.header.clone();
            Ok(Hardware {
                identity: Some(header.source.identity.clone()),
                source: Box::new(src),
                turntable: Box::new(FixedRig),
                turntable_name: "replay (recorded angles)".into(),
                poses: Poses::Frames { angles },
                angle: None,
                tilt: None,
                simulator: Vec::new(),
                device: header.device,
                capture: header.capture,
                controls: header.controls,
                replayed: Some(dir),
            })
        }
        SourceKind::Images => {
            let id = c.device_id.clone().unwrap_or_else(|| "images".into());
            let src = ImageFiles::open(&c.images, &id)?;
            let k = src.len();
            Ok(Hardware {
                identity: c.device_id.clone(),
                source: Box::new(src),
                turntable: Box::new(FixedRig),
                turntable_name: "none (photos)".into(),
                poses: Poses::Frames {
                    angles: vec![None; k],
                },
                angle: None,
                tilt: None,
                simulator: Vec::new(),
                device: None,
                capture: None,
                controls: Vec::new(),
                replayed: None,
            })
        }
        SourceKind::Synthetic => {
            let camera = cfg.synthetic.camera();
            let settings = cfg.synthetic.settings();
            if cfg.turntable.kind == TurntableKind::None {
                // A fixed rig and a person moving the camera around it.
                let poses = random_poses(rig, &camera, n, cfg.synthetic.seed);
                let fpp = cfg.camera.frames_per_pose.max(1) as usize;
                let repeated: Vec<_> = poses
                    .iter()
                    .flat_map(|p| std::iter::repeat_n(*p, fpp))
                    .collect();
                let src = SyntheticSource::new(rig.clone(), camera, repeated, settings)?;
                return Ok(Hardware {
                    identity: c.device_id.clone(),
                    source: Box::new(src),
                    turntable: Box::new(FixedRig),
                    turntable_name: "none (camera moved by hand)".into(),
                    poses: Poses::Frames {
                        angles: vec![None; n],
                    },
                    angle: None,
                    tilt: None,
                    simulator: Vec::new(),
                    device: None,
                    capture: None,
                    controls: Vec::new(),
                    replayed: None,
                });
            }
            let angle = AngleCell::default();
            let tilt = AngleCell::default();
            let base = default_view(rig, &camera);
            let (turntable, simulator, turntable_name) = open_turntable(cfg, operator)?;
            let limits = turntable.tilt_limits().map(|(a, b)| (a.0, b.0));
            let mut src = TurntableScene::new(rig.clone(), camera, base, settings, angle.clone())?;
            if limits.is_some() {
                src = src.with_tilt(tilt.clone(), cfg.turntable.geometry());
            }
            Ok(Hardware {
                identity: c.device_id.clone(),
                source: Box::new(src),
                turntable,
                turntable_name,
                poses: stage_poses(cfg, limits),
                angle: Some(angle),
                tilt: limits.map(|_| tilt),
                simulator,
                device: None,
                capture: None,
                controls: Vec::new(),
                replayed: None,
            })
        }
        SourceKind::Device => {
            let path = c.device.clone().unwrap_or_default();
            let format = match &c.fourcc {
                Some(f) => {
                    let code: [u8; 4] = f.as_bytes().try_into().map_err(|_| {
                        StationError::Config(super::config::ConfigError::Invalid {
                            origin: "station config".into(),
                            key: "camera.fourcc".into(),
                            message: format!("'{f}' is not a four-character code"),
                        })
                    })?;
                    Some(PixelFormat::from_fourcc(code).ok_or_else(|| {
                        StationError::Config(super::config::ConfigError::Invalid {
                            origin: "station config".into(),
                            key: "camera.fourcc".into(),
                            message: format!("'{f}' is not a pixel format cubecal converts"),
                        })
                    })?)
                }
                None => None,
            };
            let v4l = V4l2Config {
                width: c.width,
                height: c.height,
                format,
                fps: None,
                buffers: 4,
                lock: Some(LockSettings::default()),
            };
            let src = V4l2Source::open(&path, &v4l)?;
            let device = src.device_info().clone();
            let capture = src.negotiated();
            let controls = src.locked_controls().to_vec();
            let (turntable, simulator, turntable_name) = open_turntable(cfg, operator)?;
            let poses = if cfg.turntable.kind == TurntableKind::None {
                Poses::Frames {
                    angles: vec![None; n],
                }
            } else {
                stage_poses(cfg, turntable.tilt_limits().map(|(a, b)| (a.0, b.0)))
            };
            Ok(Hardware {
                identity: Some(device.identity()),
                source: Box::new(src),
                turntable,
                turntable_name,
                poses,
                angle: None,
                tilt: None,
                simulator,
                device: Some(device),
                capture: Some(capture),
                controls,
                replayed: None,
            })
        }
    }
}
