//! A job's frame as the user API carries it, checked once on the coordinator and read the
//! same way by every worker.

use rayfarm_core::progressive::{Progressive, Samples};
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::scene::Camera;
use rayfarm_core::schedule::speculation_depth::{Depth, parse_setting};

use crate::proto;

/// Schedule names as users type them, with their protobuf values.
pub const SCHEDULES: [(&str, proto::Schedule); 5] = [
    ("dynamic", proto::Schedule::Dynamic),
    ("image-plane", proto::Schedule::ImagePlane),
    ("domain", proto::Schedule::Domain),
    ("hybrid", proto::Schedule::Hybrid),
    ("predictive", proto::Schedule::Predictive),
];

/// The schedule called `name`.
pub fn parse_schedule(name: &str) -> Result<proto::Schedule, String> {
    SCHEDULES
        .iter()
        .find(|(n, _)| *n == name)
        .map(|&(_, s)| s)
        .ok_or_else(|| {
            let known: Vec<&str> = SCHEDULES.iter().map(|(n, _)| *n).collect();
            format!("unknown schedule {name:?} (known: {})", known.join(", "))
        })
}

/// The user-facing name of `schedule` (UNSPECIFIED means dynamic).
pub fn schedule_name(schedule: proto::Schedule) -> &'static str {
    SCHEDULES
        .iter()
        .find(|&&(_, s)| s == schedule)
        .map_or("dynamic", |(n, _)| n)
}

/// The lower-case name of a job state, as users see it.
pub fn state_name(state: proto::JobState) -> &'static str {
    match state {
        proto::JobState::Unspecified => "unknown",
        proto::JobState::Queued => "queued",
        proto::JobState::Running => "running",
        proto::JobState::Succeeded => "succeeded",
        proto::JobState::Failed => "failed",
        proto::JobState::Cancelled => "cancelled",
    }
}

/// The frame of a job: size, samples, depth and camera, checked like `render --local`'s.
/// Camera fields the job leaves empty (or a zero field of view) keep the scene's.
pub fn frame_spec(spec: &proto::JobSpec, scene_camera: &Camera) -> Result<FrameSpec, String> {
    let camera = spec
        .camera
        .as_ref()
        .map(|c| camera_from_proto(c, scene_camera))
        .transpose()?;
    let frame = FrameSpec {
        width: spec.width,
        height: spec.height,
        spp: spec.spp,
        max_depth: spec.max_depth,
        camera,
    };
    frame.check()?;
    speculation(spec)?;
    Ok(frame)
}

/// How far ahead the job's new rays are copied (`JobSpec.speculation`): `None` for no copies.
/// A setting on another schedule than predictive is refused, not ignored.
pub fn speculation(spec: &proto::JobSpec) -> Result<Option<Depth>, String> {
    let predictive = spec.schedule == proto::Schedule::Predictive as i32;
    if !predictive && !spec.speculation.is_empty() {
        return Err(format!(
            "speculation {:?} applies to the predictive schedule only",
            spec.speculation
        ));
    }
    parse_setting(&spec.speculation)
}

/// A schedule with its speculation setting, as `rayfarm bench` names them: `SCHEDULE`, or
/// `predictive:SETTING` (`none`, `full`, `ahead:N`, `predicted`, `predicted:P`).
pub fn parse_schedule_setting(name: &str) -> Result<(proto::Schedule, String), String> {
    let (schedule, setting) = match name.split_once(':') {
        Some((s, setting)) => (parse_schedule(s)?, setting.to_string()),
        None => (parse_schedule(name)?, String::new()),
    };
    if !setting.is_empty() {
        if schedule != proto::Schedule::Predictive {
            return Err(format!(
                "{name:?}: a speculation setting applies to the predictive schedule only"
            ));
        }
        parse_setting(&setting)?;
    }
    Ok((schedule, setting))
}

/// How a job cuts its samples into subframes.
pub fn progressive(spec: &proto::JobSpec) -> Progressive {
    Progressive::from_field(spec.progressive.map(|p| p.subframe_spp))
}

/// The samples a StartFrame renders of a frame of `spp` samples per pixel: its subframe's,
/// or all of them when it names none.
pub fn start_samples(s: &proto::StartFrame, spp: u32) -> Result<Samples, String> {
    if s.sample_count == 0 {
        return Ok(Samples::all(spp));
    }
    let samples = Samples {
        first: s.first_sample,
        count: s.sample_count,
    };
    if u64::from(s.first_sample) + u64::from(s.sample_count) > u64::from(spp) {
        return Err(format!(
            "StartFrame samples {}..{} outside the job's {spp} samples per pixel",
            s.first_sample,
            u64::from(s.first_sample) + u64::from(s.sample_count)
        ));
    }
    Ok(samples)
}

fn camera_from_proto(c: &proto::Camera, scene: &Camera) -> Result<Camera, String> {
    let triple = |name: &str, v: &[f32], default: [f32; 3]| -> Result<[f32; 3], String> {
        if v.is_empty() {
            return Ok(default);
        }
        v.try_into()
            .map_err(|_| format!("camera {name} needs 3 numbers, got {}", v.len()))
    };
    let camera = Camera {
        eye: triple("eye", &c.eye, scene.eye)?,
        look_at: triple("look_at", &c.look_at, scene.look_at)?,
        up: triple("up", &c.up, scene.up)?,
        fov_y_degrees: if c.fov_y_degrees == 0.0 {
            scene.fov_y_degrees
        } else {
            c.fov_y_degrees
        },
    };
    camera.check()?;
    Ok(camera)
}

/// The protobuf form of a camera.
pub fn camera_to_proto(c: &Camera) -> proto::Camera {
    proto::Camera {
        eye: c.eye.to_vec(),
        look_at: c.look_at.to_vec(),
        up: c.up.to_vec(),
        fov_y_degrees: c.fov_y_degrees,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> proto::JobSpec {
        proto::JobSpec {
            scene: "s".into(),
            camera: None,
            width: 64,
            height: 48,
            spp: 2,
            max_depth: 3,
            schedule: proto::Schedule::Dynamic as i32,
            priority: 0,
            cold_cache: false,
            progressive: None,
            speculation: String::new(),
            prefetch: false,
            peer_domains: false,
        }
    }

    const SCENE: Camera = Camera {
        eye: [0.0, 0.0, 5.0],
        look_at: [0.0; 3],
        up: [0.0, 1.0, 0.0],
        fov_y_degrees: 40.0,
    };

    #[test]
    fn empty_camera_fields_keep_the_scenes() {
        let partial = proto::JobSpec {
            camera: Some(proto::Camera {
                eye: vec![1.0, 2.0, 3.0],
                ..Default::default()
            }),
            ..spec()
        };
        let cam = frame_spec(&partial, &SCENE).unwrap().camera.unwrap();
        assert_eq!(cam.eye, [1.0, 2.0, 3.0]);
        assert_eq!(cam.look_at, SCENE.look_at);
        assert_eq!(cam.fov_y_degrees, 40.0);
    }

    #[test]
    fn absurd_frames_and_cameras_are_refused_with_the_reason() {
        assert!(frame_spec(&spec(), &SCENE).is_ok());
        let wide = proto::JobSpec {
            width: 100_000,
            ..spec()
        };
        assert!(
            frame_spec(&wide, &SCENE)
                .unwrap_err()
                .contains("resolution")
        );
        let bad_cam = proto::JobSpec {
            camera: Some(proto::Camera {
                eye: vec![0.0, 1.0],
                look_at: vec![0.0; 3],
                up: vec![],
                fov_y_degrees: 40.0,
            }),
            ..spec()
        };
        assert!(frame_spec(&bad_cam, &SCENE).unwrap_err().contains("eye"));
        assert_eq!(
            parse_schedule("image-plane"),
            Ok(proto::Schedule::ImagePlane)
        );
        assert!(parse_schedule("fastest").unwrap_err().contains("known"));
        assert_eq!(
            parse_schedule_setting("predictive:none"),
            Ok((proto::Schedule::Predictive, "none".to_string()))
        );
        assert_eq!(
            parse_schedule_setting("dynamic"),
            Ok((proto::Schedule::Dynamic, String::new()))
        );
        assert!(parse_schedule_setting("dynamic:full").is_err());
        assert!(parse_schedule_setting("predictive:sometimes").is_err());
        let mut on_dynamic = spec();
        on_dynamic.speculation = "none".into();
        assert!(
            frame_spec(&on_dynamic, &SCENE)
                .unwrap_err()
                .contains("predictive")
        );
        on_dynamic.schedule = proto::Schedule::Predictive as i32;
        assert_eq!(speculation(&on_dynamic), Ok(None));
        assert_eq!(schedule_name(proto::Schedule::Unspecified), "dynamic");
    }
}
