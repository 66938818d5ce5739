//! Synthetic cameras: frame sources that grab from the renderer ([`crate::render`]).
//! [`SyntheticSource`] renders a list of poses, one frame each; [`TurntableScene`] renders the rig at
//! the angle a (simulated) turntable last reported.

use std::time::Duration;

use super::{CaptureError, Frame, FrameSource, SourceInfo};
use crate::camera::{Camera, Pose};
use crate::render::{
    GroundTruth, LinearImage, RenderSettings, StageGeometry, SyntheticError, finish, ground_truth,
    render, render_radiance, stage_pose,
};
use crate::rig::Rig;

/// A [`FrameSource`] that renders a rig from a list of poses, one frame per pose, then reports
/// [`CaptureError::EndOfStream`]. Frames are rendered on demand, so nothing is ever queued
/// ([`FrameSource::flush`] drops nothing) and `grab` never waits (its timeout is irrelevant).
/// Timestamps are virtual: `sequence × frame_interval`.
#[derive(Debug, Clone)]
pub struct SyntheticSource {
    rig: Rig,
    camera: Camera,
    poses: Vec<Pose>,
    settings: RenderSettings,
    next: u64,
    frame_interval: Duration,
}

impl SyntheticSource {
    /// A source rendering `poses` in order. Checks the camera and settings up front.
    pub fn new(
        rig: Rig,
        camera: Camera,
        poses: Vec<Pose>,
        settings: RenderSettings,
    ) -> Result<Self, SyntheticError> {
        camera.validate().map_err(SyntheticError::Camera)?;
        settings.validate()?;
        Ok(SyntheticSource {
            rig,
            camera,
            poses,
            settings,
            next: 0,
            frame_interval: Duration::from_millis(33),
        })
    }

    /// Set the virtual time between frames (default 33 ms).
    pub fn with_frame_interval(mut self, interval: Duration) -> Self {
        self.frame_interval = interval;
        self
    }

    /// Ground truth of the frame with this sequence number, if it exists.
    pub fn ground_truth(&self, sequence: u64) -> Option<GroundTruth> {
        let pose = self.poses.get(usize::try_from(sequence).ok()?)?;
        Some(ground_truth(
            &self.rig,
            &self.camera,
            pose,
            &self.settings,
            sequence,
        ))
    }

    /// Number of frames this source produces in total.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// Whether the source produces no frames.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    fn name(&self) -> String {
        format!("synthetic:{}", self.rig.name)
    }
}

impl FrameSource for SyntheticSource {
    fn describe(&self) -> SourceInfo {
        SourceInfo {
            identity: self.name(),
            name: format!("synthetic renderer of rig '{}'", self.rig.name),
            width: self.camera.image_size[0],
            height: self.camera.image_size[1],
            format: "GREY".into(),
        }
    }

    fn grab(&mut self, _timeout: Duration) -> Result<Frame, CaptureError> {
        let Some(pose) = usize::try_from(self.next)
            .ok()
            .and_then(|k| self.poses.get(k))
        else {
            return Err(CaptureError::EndOfStream {
                source_name: self.name(),
            });
        };
        // Camera and settings were validated in `new`, so rendering cannot fail; map defensively.
        let image =
            render(&self.rig, &self.camera, pose, &self.settings, self.next).map_err(|e| {
                CaptureError::Io {
                    source_name: self.name(),
                    context: format!("rendering frame {}", self.next),
                    source: std::io::Error::other(e),
                }
            })?;
        let frame = Frame {
            sequence: self.next,
            timestamp: self.frame_interval * u32::try_from(self.next).unwrap_or(u32::MAX),
            image,
        };
        self.next += 1;
        Ok(frame)
    }

    fn flush(&mut self) -> Result<usize, CaptureError> {
        Ok(0)
    }
}

/// The angle a turntable last reported, shared between the station (which writes it after every
/// settled move) and a [`TurntableScene`] (which renders the rig at it). Degrees; starts at 0.
#[derive(Debug, Clone, Default)]
pub struct AngleCell(std::sync::Arc<std::sync::atomic::AtomicU64>);

impl AngleCell {
    pub fn set(&self, degrees: f64) {
        self.0
            .store(degrees.to_bits(), std::sync::atomic::Ordering::SeqCst);
    }
    pub fn get(&self) -> f64 {
        f64::from_bits(self.0.load(std::sync::atomic::Ordering::SeqCst))
    }
}

/// A synthetic camera in front of a turntable: every frame renders the rig at the angle the turntable
/// last reported ([`AngleCell`]), and at the tilt its cradle last reported when it has one
/// ([`TurntableScene::with_tilt`]), so a stage that settles in the wrong place shows in the images.
/// Consecutive frames at the same angle share one radiance render (only the noise differs), as a
/// real camera's frames of a still scene do. [`TurntableScene::with_camera_change`] swaps the camera
/// from a given frame on (a focus or zoom change mid-run, for tests of the verdict).
#[derive(Debug, Clone)]
pub struct TurntableScene {
    rig: Rig,
    camera: Camera,
    base: Pose,
    settings: RenderSettings,
    angle: AngleCell,
    tilt: AngleCell,
    geometry: StageGeometry,
    change: Option<(u64, Camera)>,
    next: u64,
    frame_interval: Duration,
    cache: Option<(f64, f64, u64, std::sync::Arc<LinearImage>)>,
}

impl TurntableScene {
    /// A scene with the camera at `base` (`cam_from_rig` at 0°), e.g. [`crate::render::default_view`].
    pub fn new(
        rig: Rig,
        camera: Camera,
        base: Pose,
        settings: RenderSettings,
        angle: AngleCell,
    ) -> Result<Self, SyntheticError> {
        camera.validate().map_err(SyntheticError::Camera)?;
        settings.validate()?;
        Ok(TurntableScene {
            rig,
            camera,
            base,
            settings,
            angle,
            tilt: AngleCell::default(),
            geometry: StageGeometry::default(),
            change: None,
            next: 0,
            frame_interval: Duration::from_millis(33),
            cache: None,
        })
    }

    /// Put the rig on a two-axis stage: `geometry` says where it sits relative to the axes
    /// ([`stage_pose`]), `tilt` is the angle the tilt axis last reported.
    pub fn with_tilt(mut self, tilt: AngleCell, geometry: StageGeometry) -> Self {
        self.tilt = tilt;
        self.geometry = geometry;
        self
    }

    /// From frame `sequence` on, render with `camera` instead.
    pub fn with_camera_change(
        mut self,
        sequence: u64,
        camera: Camera,
    ) -> Result<Self, SyntheticError> {
        camera.validate().map_err(SyntheticError::Camera)?;
        self.change = Some((sequence, camera));
        Ok(self)
    }

    /// The camera that renders frame `sequence`.
    pub fn camera_at(&self, sequence: u64) -> &Camera {
        match &self.change {
            Some((from, cam)) if sequence >= *from => cam,
            _ => &self.camera,
        }
    }

    /// `cam_from_rig` of the rig at `angle_deg` and the stage's current tilt.
    pub fn pose_at(&self, angle_deg: f64) -> Pose {
        self.pose_at_tilt(angle_deg, self.tilt.get())
    }

    /// `cam_from_rig` of the rig at `angle_deg` and `tilt_deg`.
    pub fn pose_at_tilt(&self, angle_deg: f64, tilt_deg: f64) -> Pose {
        stage_pose(&self.rig, &self.base, &self.geometry, angle_deg, tilt_deg)
    }

    fn name(&self) -> String {
        format!("synthetic:{}", self.rig.name)
    }
}

impl FrameSource for TurntableScene {
    fn describe(&self) -> SourceInfo {
        SourceInfo {
            identity: self.name(),
            name: format!(
                "synthetic camera in front of a turntable carrying rig '{}'",
                self.rig.name
            ),
            width: self.camera.image_size[0],
            height: self.camera.image_size[1],
            format: "GREY".into(),
        }
    }

    fn grab(&mut self, _timeout: Duration) -> Result<Frame, CaptureError> {
        let angle = self.angle.get();
        let tilt = self.tilt.get();
        let seq = self.next;
        let camera = self.camera_at(seq).clone();
        let generation = match &self.change {
            Some((from, _)) if seq >= *from => 1,
            _ => 0,
        };
        let radiance = match &self.cache {
            Some((a, t, g, img)) if *a == angle && *t == tilt && *g == generation => img.clone(),
            _ => {
                let pose = self.pose_at_tilt(angle, tilt);
                let img =
                    render_radiance(&self.rig, &camera, &pose, &self.settings).map_err(|e| {
                        CaptureError::Io {
                            source_name: self.name(),
                            context: format!("rendering frame {seq} at {angle}°, tilt {tilt}°"),
                            source: std::io::Error::other(e),
                        }
                    })?;
                let img = std::sync::Arc::new(img);
                self.cache = Some((angle, tilt, generation, img.clone()));
                img
            }
        };
        let image = finish(&radiance, &camera, &self.settings, seq);
        self.next += 1;
        Ok(Frame {
            sequence: seq,
            timestamp: self.frame_interval * u32::try_from(seq).unwrap_or(u32::MAX),
            image,
        })
    }

    fn flush(&mut self) -> Result<usize, CaptureError> {
        Ok(0)
    }
}
