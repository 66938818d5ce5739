//! Camera controls: list them, and lock the ones that change the intrinsics or the image between poses.
//!
//! Locking means: automatic focus, exposure, gain and white balance off, zoom fixed, and each fixed
//! value either the one requested in [`LockSettings`] or the value the device had when the automatic
//! mode was switched off. Every value is read back after it is set; the values the driver actually
//! accepted (drivers clamp and round) are what goes into the session and the profile.

use v4l::control::{Control, Type, Value};
use v4l::device::Device;

use crate::capture::CaptureError;

// Control IDs from <linux/videodev2.h> (V4L2_CID_BASE = 0x00980900, V4L2_CID_CAMERA_CLASS_BASE = 0x009a0900).
pub const CID_AUTO_WHITE_BALANCE: u32 = 0x0098_090c;
pub const CID_AUTOGAIN: u32 = 0x0098_0912;
pub const CID_GAIN: u32 = 0x0098_0913;
pub const CID_WHITE_BALANCE_TEMPERATURE: u32 = 0x0098_091a;
pub const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
pub const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
pub const CID_EXPOSURE_AUTO_PRIORITY: u32 = 0x009a_0903;
pub const CID_FOCUS_ABSOLUTE: u32 = 0x009a_090a;
pub const CID_FOCUS_AUTO: u32 = 0x009a_090c;
pub const CID_ZOOM_ABSOLUTE: u32 = 0x009a_090d;
pub const CID_ZOOM_CONTINUOUS: u32 = 0x009a_090f;
pub const CID_AUTO_N_PRESET_WHITE_BALANCE: u32 = 0x009a_0914;
/// `V4L2_EXPOSURE_MANUAL` for [`CID_EXPOSURE_AUTO`].
const EXPOSURE_MANUAL: i64 = 1;
/// `V4L2_WHITE_BALANCE_MANUAL` for [`CID_AUTO_N_PRESET_WHITE_BALANCE`].
const WHITE_BALANCE_MANUAL: i64 = 0;

// V4L2_CTRL_FLAG_*
const FLAG_DISABLED: u32 = 0x0001;
const FLAG_READ_ONLY: u32 = 0x0004;
const FLAG_INACTIVE: u32 = 0x0010;
const FLAG_WRITE_ONLY: u32 = 0x0040;

/// One control as the device describes it, with its current value when it has a scalar one.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ControlInfo {
    pub id: u32,
    pub name: String,
    /// "integer", "boolean", "menu", "button", …
    pub kind: String,
    pub minimum: i64,
    pub maximum: i64,
    pub step: u64,
    pub default: i64,
    /// Current value (scalar controls that can be read only).
    pub value: Option<i64>,
    /// Menu items `(index, label)` for menu controls.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub menu: Vec<(u32, String)>,
    pub read_only: bool,
    pub inactive: bool,
}

/// Fixed values to use when locking; `None` keeps the value the device has once its automatic mode is
/// off.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LockSettings {
    pub focus: Option<i64>,
    /// Exposure in the driver's unit (`exposure_time_absolute`: 100 µs).
    pub exposure: Option<i64>,
    pub gain: Option<i64>,
    /// White balance temperature in kelvin.
    pub white_balance_k: Option<i64>,
    pub zoom: Option<i64>,
}

/// A control value cubecal set, and what the driver accepted (read back after setting).
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ControlSetting {
    pub id: u32,
    pub name: String,
    pub requested: i64,
    pub accepted: i64,
}

fn kind_name(t: Type) -> &'static str {
    match t {
        Type::Integer => "integer",
        Type::Boolean => "boolean",
        Type::Menu => "menu",
        Type::Button => "button",
        Type::Integer64 => "integer64",
        Type::CtrlClass => "class",
        Type::String => "string",
        Type::Bitmask => "bitmask",
        Type::IntegerMenu => "integer-menu",
        _ => "compound",
    }
}

fn is_scalar(t: Type) -> bool {
    matches!(
        t,
        Type::Integer
            | Type::Boolean
            | Type::Menu
            | Type::Integer64
            | Type::IntegerMenu
            | Type::Bitmask
    )
}

fn as_i64(v: &Value) -> Option<i64> {
    match v {
        Value::Integer(x) => Some(*x),
        Value::Boolean(b) => Some(*b as i64),
        _ => None,
    }
}

/// Every control of the device, with current values of the scalar ones.
pub fn list_controls(dev: &Device, device: &str) -> Result<Vec<ControlInfo>, CaptureError> {
    let descs = dev.query_controls().map_err(|e| {
        CaptureError::from_io(device, "listing controls (VIDIOC_QUERY_EXT_CTRL)", e)
    })?;
    let mut out = Vec::with_capacity(descs.len());
    for d in descs {
        let flags = u32::from(d.flags);
        if flags & FLAG_DISABLED != 0 || d.typ == Type::CtrlClass {
            continue;
        }
        let value = if is_scalar(d.typ) && flags & FLAG_WRITE_ONLY == 0 {
            dev.control(d.id).ok().and_then(|c| as_i64(&c.value))
        } else {
            None
        };
        let menu = d
            .items
            .as_ref()
            .map(|items| items.iter().map(|(i, it)| (*i, it.to_string())).collect())
            .unwrap_or_default();
        out.push(ControlInfo {
            id: d.id,
            name: d.name.clone(),
            kind: kind_name(d.typ).to_string(),
            minimum: d.minimum,
            maximum: d.maximum,
            step: d.step,
            default: d.default,
            value,
            menu,
            read_only: flags & FLAG_READ_ONLY != 0,
            inactive: flags & FLAG_INACTIVE != 0,
        });
    }
    Ok(out)
}

/// Set one scalar control and read back what the driver accepted.
pub fn set_control(
    dev: &Device,
    device: &str,
    info: &ControlInfo,
    value: i64,
) -> Result<ControlSetting, CaptureError> {
    let v = if info.kind == "boolean" {
        Value::Boolean(value != 0)
    } else {
        Value::Integer(value)
    };
    let ctx = |what: &str| format!("{what} control {:?} ({:#x})", info.name, info.id);
    dev.set_control(Control {
        id: info.id,
        value: v,
    })
    .map_err(|e| CaptureError::Control {
        device: device.to_string(),
        context: ctx("setting"),
        source: e,
    })?;
    let back = dev.control(info.id).map_err(|e| CaptureError::Control {
        device: device.to_string(),
        context: ctx("reading back"),
        source: e,
    })?;
    let accepted = as_i64(&back.value).unwrap_or(value);
    if accepted != value {
        tracing::warn!(device, control = %info.name, requested = value, accepted, "driver adjusted a control value");
    }
    Ok(ControlSetting {
        id: info.id,
        name: info.name.clone(),
        requested: value,
        accepted,
    })
}

/// Lock the controls that change the intrinsics or the image between poses. Controls the device does
/// not have are skipped (logged at debug level). Order matters: an automatic mode is switched off
/// before its manual value is written (many UVC cameras refuse the value while the mode is automatic).
pub fn lock_controls(
    dev: &Device,
    device: &str,
    want: &LockSettings,
) -> Result<Vec<ControlSetting>, CaptureError> {
    // (auto-mode control, value that means "manual"), then (value control, requested value)
    let plan: [(u32, Option<i64>); 12] = [
        (CID_FOCUS_AUTO, Some(0)),
        (CID_FOCUS_ABSOLUTE, want.focus),
        (CID_EXPOSURE_AUTO, Some(EXPOSURE_MANUAL)),
        (CID_EXPOSURE_AUTO_PRIORITY, Some(0)),
        (CID_EXPOSURE_ABSOLUTE, want.exposure),
        (CID_AUTOGAIN, Some(0)),
        (CID_GAIN, want.gain),
        (CID_AUTO_WHITE_BALANCE, Some(0)),
        (CID_AUTO_N_PRESET_WHITE_BALANCE, Some(WHITE_BALANCE_MANUAL)),
        (CID_WHITE_BALANCE_TEMPERATURE, want.white_balance_k),
        (CID_ZOOM_CONTINUOUS, Some(0)),
        (CID_ZOOM_ABSOLUTE, want.zoom),
    ];
    let mut locked = Vec::new();
    for (id, value) in plan {
        // re-list each time: switching an automatic mode off changes which controls are active
        let Some(info) = list_controls(dev, device)?.into_iter().find(|c| c.id == id) else {
            tracing::debug!(
                device,
                id = format_args!("{id:#x}"),
                "control not offered; not locked"
            );
            continue;
        };
        if info.read_only {
            tracing::debug!(device, control = %info.name, "read-only control; not locked");
            continue;
        }
        // A value control without a requested value is pinned at its current value: writing it makes the
        // driver leave any automatic state, and the read-back records it.
        match (value, info.value) {
            // an automatic mode switched off, or a value the user asked for: failure is an error,
            // because the camera would not be in the state the calibration assumes
            (Some(v), _) => locked.push(set_control(dev, device, &info, v)?),
            // pinning the current value: some drivers refuse to write a value they report (e.g.
            // marked inactive); the value is still fixed once its automatic mode is off, so record it
            (None, Some(current)) => match set_control(dev, device, &info, current) {
                Ok(s) => locked.push(s),
                Err(e) => {
                    tracing::warn!(device, control = %info.name, current, error = %e, "could not re-write the current value; recording it as read");
                    locked.push(ControlSetting {
                        id: info.id,
                        name: info.name.clone(),
                        requested: current,
                        accepted: current,
                    });
                }
            },
            (None, None) => {}
        }
    }
    Ok(locked)
}
