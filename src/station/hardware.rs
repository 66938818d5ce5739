//! Opening what a station run needs from its configuration: the frame source and the turntable,
//! including the built-in protocol simulators on a pseudo-terminal and the synthetic camera that
//! renders the rig at the angle the turntable reports.

use std::path::PathBuf;
use std::time::Duration;

use super::StationError;
use super::config::{SourceKind, StationConfig, TurntableKind};
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
    /// A sequence of frames that arrive by themselves (replayed session, photos, a person moving
    /// the camera in front of a fixed rig): `n` poses of `frames_per_pose` frames, with the angle
    /// recorded for each pose when known.
    Frames { angles: Vec<Option<f64>> },
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
    /// Keeps a protocol simulator alive for the run.
    pub simulator: Option<SimHandle>,
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

/// A turntable, the simulator serving it (if any) and its description.
pub type OpenedTurntable = (Box<dyn Turntable>, Option<SimHandle>, String);

/// Open the turntable the config names. `operator` answers a manual turntable's prompts.
pub fn open_turntable(
    cfg: &StationConfig,
    operator: Option<Box<dyn Operator>>,
) -> Result<OpenedTurntable, StationError> {
    let t = &cfg.turntable;
    let move_timeout = Duration::from_secs(t.move_timeout_s);
    let exchange_timeout = Duration::from_millis(t.reply_timeout_ms);
    let grbl_config = GrblConfig {
        exchange_timeout,
        move_timeout,
        home_timeout: move_timeout * 2,
        ..GrblConfig::new(Axis::A, t.degrees_per_unit)
    };
    let zaber_config = ZaberConfig {
        exchange_timeout,
        move_timeout,
        home_timeout: move_timeout * 2,
        ..ZaberConfig::new(t.microsteps_per_degree)
    };
    let port_path = || t.port.clone().unwrap_or_default();
    Ok(match t.kind {
        TurntableKind::None => (Box::new(FixedRig), None, "none (fixed rig)".into()),
        TurntableKind::Manual => {
            let op = operator.ok_or_else(|| StationError::NoOperator)?;
            (
                Box::new(ManualTurntable::new(op, MANUAL_RESOLUTION)?),
                None,
                "manual (operator prompts)".into(),
            )
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
                    axis: Axis::A,
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
                    device: 1,
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
                simulator: None,
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
                simulator: None,
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
                    simulator: None,
                    device: None,
                    capture: None,
                    controls: Vec::new(),
                    replayed: None,
                });
            }
            let angle = AngleCell::default();
            let base = default_view(rig, &camera);
            let src = TurntableScene::new(rig.clone(), camera, base, settings, angle.clone())?;
            let (turntable, simulator, turntable_name) = open_turntable(cfg, operator)?;
            Ok(Hardware {
                identity: c.device_id.clone(),
                source: Box::new(src),
                turntable,
                turntable_name,
                poses: Poses::Angles(plan_angles(n, cfg.plan.sweep_deg)),
                angle: Some(angle),
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
                Poses::Angles(plan_angles(n, cfg.plan.sweep_deg))
            };
            Ok(Hardware {
                identity: Some(device.identity()),
                source: Box::new(src),
                turntable,
                turntable_name,
                poses,
                angle: None,
                simulator,
                device: Some(device),
                capture: Some(capture),
                controls,
                replayed: None,
            })
        }
    }
}
