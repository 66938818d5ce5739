//! `cubecal turntable ...`: bring-up commands for a serial turntable (probe, home, move, status) and a
//! protocol simulator on a pseudo-terminal. Parse the arguments, validate them into driver configs,
//! run, render (human text or `--json`). Port-access hints (dialout group, udev rule) live here.

use serialport::SerialPort;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::{Args, Subcommand, ValueEnum};
use cubecal::exit;
use cubecal::turntable::grbl::{Axis, GrblConfig, GrblTurntable};
use cubecal::turntable::manual::{FixedRig, MANUAL_RESOLUTION, ManualTurntable};

use super::operator::TerminalOperator;
use cubecal::turntable::serial::open_port;
use cubecal::turntable::sim::{self, Fault, GrblSim, SimConfig, ZaberSim};
use cubecal::turntable::zaber::{X_RSW60A_MICROSTEPS_PER_DEGREE, ZaberConfig, ZaberTurntable};
use cubecal::turntable::{DEFAULT_RETRIES, Degrees, Turntable, TurntableError};

use cubecal::capture::convert::PixelFormat;
use cubecal::capture::feed::{FeedConfig, Feeder};
use cubecal::capture::synthetic::{AngleCell, TurntableScene};
use cubecal::render::default_view;
use cubecal::turntable::sim::StageView;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use super::{Output, UsageError};

#[derive(Debug, Subcommand)]
pub enum TurntableCommand {
    /// Open the port, identify the turntable (firmware) and read its position.
    Probe(Conn),
    /// Home the turntable (find its reference position).
    Home(Conn),
    /// Move to an absolute angle and wait until the stage reports it has settled.
    Move {
        /// Target angle in degrees (absolute, may be negative).
        #[arg(allow_negative_numbers = true)]
        angle: f64,
        #[command(flatten)]
        conn: Conn,
    },
    /// Print the current position.
    Status(Conn),
    /// Serve a simulated turntable on a pseudo-terminal; prints the port path to use with --port.
    Simulate(SimulateArgs),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ProtocolArg {
    /// GRBL 1.1 G-code controller.
    Grbl,
    /// Zaber ASCII protocol.
    Zaber,
    /// A hand-turned table: the operator turns it and confirms on the terminal.
    Manual,
    /// No turntable (fixed rig).
    None,
}

/// How to reach the turntable.
#[derive(Debug, Args)]
pub struct Conn {
    /// Serial port path, e.g. /dev/ttyUSB0 (required for grbl and zaber).
    #[arg(long, required_if_eq_any = [("protocol", "grbl"), ("protocol", "zaber")])]
    port: Option<String>,
    /// Protocol spoken by the turntable.
    #[arg(long, value_enum)]
    protocol: ProtocolArg,
    /// Baud rate.
    #[arg(long, default_value_t = 115_200)]
    baud: u32,
    #[command(flatten)]
    drive: DriveArgs,
    /// Reply timeout for one exchange, in milliseconds.
    #[arg(long, default_value_t = 500)]
    timeout_ms: u64,
    /// Re-sends after a missing or garbled reply.
    #[arg(long, default_value_t = DEFAULT_RETRIES)]
    retries: u32,
    /// Limit for one move, in seconds (homing gets twice this).
    #[arg(long, default_value_t = 60)]
    move_timeout_s: u64,
}

/// Protocol-specific mechanics (shared by the drivers and the simulator).
#[derive(Debug, Args)]
pub struct DriveArgs {
    /// GRBL: axis letter the table is wired to (X, Y, Z, A, B, C).
    #[arg(long, default_value = "X", value_parser = parse_axis)]
    axis: Axis,
    /// GRBL: degrees of rotation per GRBL unit.
    #[arg(long, default_value_t = 1.0)]
    degrees_per_unit: f64,
    /// GRBL: home with $H (homing switches configured) instead of $X and a move to 0.
    #[arg(long)]
    homing: bool,
    /// Zaber: microsteps per degree (default: X-RSW60A, 0.000234375° per microstep).
    #[arg(long, default_value_t = X_RSW60A_MICROSTEPS_PER_DEGREE)]
    microsteps_per_degree: f64,
    /// Zaber: device address on the chain.
    #[arg(long, default_value_t = 1)]
    device: u8,
    /// Zaber: axis number on the device.
    #[arg(long, default_value_t = 1)]
    zaber_axis: u8,
}

fn parse_axis(s: &str) -> Result<Axis, String> {
    let mut chars = s.chars();
    match (chars.next().and_then(Axis::from_letter), chars.next()) {
        (Some(a), None) => Ok(a),
        _ => Err(format!("expected one of X, Y, Z, A, B, C, got {s:?}")),
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SimProtocol {
    Grbl,
    Zaber,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FaultArg {
    NoReply,
    Garbage,
    Alarm,
    LostSteps,
    PortClosed,
}

#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Protocol to simulate.
    #[arg(long, value_enum)]
    protocol: SimProtocol,
    /// Stop after this many seconds (default: serve until Ctrl-C).
    #[arg(long)]
    seconds: Option<u64>,
    /// Cruise speed, degrees per second.
    #[arg(long, default_value_t = 30.0)]
    speed_deg_s: f64,
    /// Acceleration, degrees per second squared.
    #[arg(long, default_value_t = 60.0)]
    accel_deg_s2: f64,
    /// Inject a fault on the first move command (lost-steps: every move ends 0.5° past its target).
    #[arg(long, value_enum)]
    fault: Option<FaultArg>,
    /// Also make PATH a symbolic link to the pseudo-terminal (replacing an existing link), e.g. the
    /// station service's port /dev/cubecal-turntable; removed on exit.
    #[arg(long, value_name = "PATH")]
    link: Option<std::path::PathBuf>,
    #[command(flatten)]
    drive: DriveArgs,
    #[command(flatten)]
    feed: FeedArgs,
}

/// A camera for the simulated table: the rig rendered at the simulator's angle, written to a V4L2
/// output device (cubecal::capture::feed; GRBL only).
#[derive(Debug, Args)]
pub struct FeedArgs {
    /// V4L2 output node to write the rendered rig to (e.g. vivid's HDMI output, looped into its
    /// capture node); waits for the node to appear.
    #[arg(long, value_name = "DEVICE", requires = "station_config")]
    feed: Option<std::path::PathBuf>,
    /// Station config whose [synthetic] camera, [rig] and camera.fourcc the feeder renders with (the
    /// station reading the capture node must use the same config).
    #[arg(long, value_name = "CONFIG", requires = "feed")]
    station_config: Option<std::path::PathBuf>,
    /// A vivid capture node to switch to looping the output (Loop Video on, OSD text off).
    #[arg(long, value_name = "DEVICE", requires = "feed")]
    vivid_loop: Option<std::path::PathBuf>,
    /// How long to wait for the output node (and the --vivid-loop node) to appear, seconds.
    #[arg(long, default_value_t = 300)]
    feed_wait_s: u64,
}

pub fn run(cmd: TurntableCommand, out: Output) -> anyhow::Result<u8> {
    match cmd {
        TurntableCommand::Probe(conn) => {
            let mut t = conn.open()?;
            let device = t.describe()?;
            let pos = t.position()?;
            render(
                out,
                &format!("{device}\nposition {pos}, resolution {}", t.resolution()),
                serde_json::json!({
                    "device": device,
                    "position_deg": pos.0,
                    "resolution_deg": t.resolution().0,
                }),
            )?;
        }
        TurntableCommand::Home(conn) => {
            let mut t = conn.open()?;
            let start = Instant::now();
            let pos = t.home()?;
            render(
                out,
                &format!(
                    "homed: position {pos} ({:.2} s)",
                    start.elapsed().as_secs_f64()
                ),
                serde_json::json!({ "position_deg": pos.0, "elapsed_s": start.elapsed().as_secs_f64() }),
            )?;
        }
        TurntableCommand::Move { angle, conn } => {
            let target = Degrees::checked(angle)?;
            let mut t = conn.open()?;
            let start = Instant::now();
            let pos = t.move_to(target)?;
            render(
                out,
                &format!(
                    "settled at {pos} (target {target}, {:.2} s)",
                    start.elapsed().as_secs_f64()
                ),
                serde_json::json!({
                    "target_deg": target.0,
                    "position_deg": pos.0,
                    "elapsed_s": start.elapsed().as_secs_f64(),
                }),
            )?;
        }
        TurntableCommand::Status(conn) => {
            let mut t = conn.open()?;
            let pos = t.position()?;
            render(
                out,
                &format!("position {pos}"),
                serde_json::json!({ "position_deg": pos.0, "resolution_deg": t.resolution().0 }),
            )?;
        }
        TurntableCommand::Simulate(args) => simulate(args, out)?,
    }
    Ok(exit::SUCCESS)
}

fn render(out: Output, human: &str, json: serde_json::Value) -> anyhow::Result<()> {
    if out.json {
        outln!("{json}")?;
    } else {
        outln!("{human}")?;
    }
    Ok(())
}

impl Conn {
    /// Validate the arguments into a driver and open the port.
    fn open(&self) -> anyhow::Result<Box<dyn Turntable>> {
        let exchange_timeout = Duration::from_millis(self.timeout_ms);
        let move_timeout = Duration::from_secs(self.move_timeout_s);
        let d = &self.drive;
        match self.protocol {
            ProtocolArg::None => Ok(Box::new(FixedRig)),
            ProtocolArg::Manual => Ok(Box::new(ManualTurntable::new(
                TerminalOperator,
                MANUAL_RESOLUTION,
            )?)),
            ProtocolArg::Grbl => {
                let config = GrblConfig {
                    homing: d.homing,
                    exchange_timeout,
                    status_retries: self.retries,
                    move_timeout,
                    home_timeout: move_timeout * 2,
                    ..GrblConfig::new(d.axis, d.degrees_per_unit)
                };
                let port = self.open_port()?;
                Ok(Box::new(GrblTurntable::new(port, config)?))
            }
            ProtocolArg::Zaber => {
                let config = ZaberConfig {
                    device: d.device,
                    axis: d.zaber_axis,
                    exchange_timeout,
                    retries: self.retries,
                    move_timeout,
                    home_timeout: move_timeout * 2,
                    ..ZaberConfig::new(d.microsteps_per_degree)
                };
                let port = self.open_port()?;
                Ok(Box::new(ZaberTurntable::new(port, config)?))
            }
        }
    }

    fn open_port(&self) -> anyhow::Result<Box<dyn serialport::SerialPort>> {
        let path = self
            .port
            .as_deref()
            .ok_or_else(|| TurntableError::InvalidConfig {
                field: "--port",
                reason: "required for --protocol grbl and zaber".into(),
            })?;
        open_port(path, self.baud).map_err(|e| {
            let hint = match &e {
                TurntableError::PermissionDenied { .. } => Some(
                    "join the `dialout` group (sudo usermod -aG dialout $USER, then log out and in) \
                     or install udev/99-cubecal.rules into /etc/udev/rules.d/",
                ),
                TurntableError::PortNotFound { .. } => Some(
                    "check the cable and the path (ls /dev/ttyUSB* /dev/ttyACM* /dev/serial/by-id/)",
                ),
                TurntableError::PortBusy { .. } => Some(
                    "close the other program using it (fuser -v PATH shows which)",
                ),
                _ => None,
            };
            match hint {
                Some(h) => anyhow::Error::new(e).context(format!("turntable port unavailable: {h}")),
                None => e.into(),
            }
        })
    }
}

#[allow(clippy::print_stdout)]
fn simulate(args: SimulateArgs, out: Output) -> anyhow::Result<()> {
    let d = &args.drive;
    // The simulators work in native units: GRBL axis units, Zaber microsteps.
    let per_degree = match args.protocol {
        SimProtocol::Grbl => 1.0 / d.degrees_per_unit,
        SimProtocol::Zaber => d.microsteps_per_degree,
    };
    if !(per_degree.is_finite() && per_degree != 0.0) {
        return Err(TurntableError::InvalidConfig {
            field: "--degrees-per-unit/--microsteps-per-degree",
            reason: "must be finite and non-zero".into(),
        }
        .into());
    }
    let fault = args.fault.map(|f| match f {
        FaultArg::NoReply => Fault::NoReply,
        FaultArg::Garbage => Fault::Garbage,
        FaultArg::Alarm => Fault::AlarmMidMove,
        FaultArg::LostSteps => Fault::LostSteps {
            offset: 0.5 * per_degree,
        },
        FaultArg::PortClosed => Fault::PortClosed,
    });
    let config = SimConfig {
        speed: args.speed_deg_s * per_degree.abs(),
        accel: args.accel_deg_s2 * per_degree.abs(),
        fault,
    };
    let grbl = GrblSim {
        axis: d.axis,
        homing: d.homing,
    };
    let feeding = match (&args.feed.feed, args.protocol) {
        (Some(_), SimProtocol::Zaber) => {
            return Err(UsageError("--feed works with --protocol grbl only".into()).into());
        }
        (Some(output), SimProtocol::Grbl) => Some(feed_setup(&args.feed, output, d)?),
        (None, _) => None,
    };
    let view = feeding.as_ref().map(|f| f.view.clone());
    let (slave, handle) = match args.protocol {
        SimProtocol::Grbl => match view {
            Some(view) => sim::grbl_pair_seen(config, grbl, view)?,
            None => sim::grbl_pair(config, grbl)?,
        },
        SimProtocol::Zaber => sim::zaber_pair(
            config,
            ZaberSim {
                device: d.device,
                limit_microsteps: (cubecal::turntable::MAX_ABS_DEGREES * d.microsteps_per_degree)
                    as i64,
            },
        )?,
    };
    // Keep the slave end open for as long as we serve: with no slave open, the master reads EIO.
    let path = slave.name().context("the pseudo-terminal has no path")?;
    if let Some(link) = &args.link {
        replace_link(&path, link)?;
    }
    let shown_port = args
        .link
        .as_ref()
        .map(|l| l.display().to_string())
        .unwrap_or_else(|| path.clone());
    let protocol = match args.protocol {
        SimProtocol::Grbl => "grbl",
        SimProtocol::Zaber => "zaber",
    };
    let feeder = match feeding {
        Some(f) => Some(Feeder::spawn(f.scene, f.angle, f.view, f.config)?),
        None => None,
    };
    if out.json {
        outln!(
            "{}",
            serde_json::json!({ "protocol": protocol, "port": path, "link": args.link, "feed": args.feed.feed })
        )?;
    } else {
        outln!("{protocol} simulator on {path}")?;
        if let Some(output) = &args.feed.feed {
            outln!("feeding the rendered rig to {}", output.display())?;
        }
        outln!(
            "try: cubecal turntable probe --protocol {protocol} --port {shown_port}  (Ctrl-C to stop)"
        )?;
    }
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register(sig, Arc::clone(&stop))
            .context("installing the signal handler")?;
    }
    let until = args
        .seconds
        .map(|s| Instant::now() + Duration::from_secs(s));
    while handle.is_running()
        && feeder.as_ref().is_none_or(Feeder::is_running)
        && !stop.load(Ordering::Relaxed)
        && until.is_none_or(|u| Instant::now() < u)
    {
        std::thread::sleep(Duration::from_millis(50));
    }
    let fed = feeder.map(|f| {
        tracing::info!(
            renders = f.stats().renders(),
            writes = f.stats().writes(),
            render_s = f.stats().render_time().as_secs_f64(),
            "feeder stopping"
        );
        f.stop()
    });
    handle.stop();
    drop(slave);
    if let Some(link) = &args.link {
        let _ = std::fs::remove_file(link);
    }
    if let Some(result) = fed {
        result.context("the feeder stopped")?;
    }
    Ok(())
}

/// What the feeder needs, prepared before the simulator starts.
struct Feeding {
    scene: TurntableScene,
    angle: AngleCell,
    view: StageView,
    config: FeedConfig,
}

/// The scene of the station config: its rig, its synthetic camera in the default view, and the capture
/// format the station asks for (vivid loops only identical formats).
fn feed_setup(args: &FeedArgs, output: &std::path::Path, d: &DriveArgs) -> anyhow::Result<Feeding> {
    let station_config = args
        .station_config
        .clone()
        .ok_or_else(|| UsageError("--feed needs --station-config".into()))?;
    // The feeder is this config's synthetic camera: its camera.device (the capture node the station
    // reads) is not needed here.
    let prepared =
        cubecal::station::setup::prepare(&cubecal::station::setup::RunRequest::from_config(
            station_config.clone(),
            None,
            vec!["camera.source=\"synthetic\"".into()],
        ))?;
    let cfg = &prepared.cfg;
    let fourcc = cfg.camera.fourcc.as_deref().ok_or_else(|| {
        UsageError(format!(
            "{}: --feed needs camera.fourcc, so that the station captures in the format the feeder writes",
            station_config.display()
        ))
    })?;
    let format = <[u8; 4]>::try_from(fourcc.as_bytes())
        .ok()
        .and_then(PixelFormat::from_fourcc)
        .ok_or_else(|| {
            UsageError(format!(
                "camera.fourcc '{fourcc}' is not a format cubecal converts"
            ))
        })?;
    let camera = cfg.synthetic.camera();
    let angle = AngleCell::default();
    let base = default_view(&prepared.rig, &camera);
    let scene = TurntableScene::new(
        prepared.rig.clone(),
        camera,
        base,
        cfg.synthetic.settings(),
        angle.clone(),
    )?;
    Ok(Feeding {
        scene,
        angle,
        view: StageView::default(),
        config: FeedConfig {
            output: output.to_path_buf(),
            format,
            degrees_per_unit: d.degrees_per_unit,
            vivid_loop: args.vivid_loop.clone(),
            buffers: 4,
            wait_for_device: Duration::from_secs(args.feed_wait_s),
        },
    })
}

/// Point `link` at `target`, replacing an existing link (never a regular file or a device node).
fn replace_link(target: &str, link: &std::path::Path) -> anyhow::Result<()> {
    if let Ok(meta) = std::fs::symlink_metadata(link) {
        if !meta.file_type().is_symlink() {
            return Err(UsageError(format!(
                "--link {}: exists and is not a symbolic link",
                link.display()
            ))
            .into());
        }
        std::fs::remove_file(link).with_context(|| format!("removing {}", link.display()))?;
    }
    std::os::unix::fs::symlink(target, link)
        .with_context(|| format!("linking {} to {target}", link.display()))
}
