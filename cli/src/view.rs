//! The frame and camera flags that `render` and `submit` share, with the same names, defaults,
//! environment twins and checks, so a frame described once renders the same way locally and
//! on the cluster. Camera values are checked by the core's camera check as they are parsed;
//! the whole camera (eye against look-at, up against the view) is checked where the scene's
//! camera is known: `render` here, jobs on the coordinator, both with `Camera::check`.

use clap::Args;
use rayfarm_core::scene::Camera;
use rayfarm_core::scene::manifest::{check_fov, check_up};
use rayfarm_node::proto;

use crate::units;

/// Size, samples and depth of a frame.
#[derive(Args, Clone, Debug)]
pub struct FrameArgs {
    /// Image width.
    #[arg(long, env = "RAYFARM_WIDTH", default_value_t = 640)]
    pub width: u32,
    /// Image height.
    #[arg(long, env = "RAYFARM_HEIGHT", default_value_t = 480)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, env = "RAYFARM_SPP", default_value_t = 4)]
    pub spp: u32,
    /// Maximum bounces.
    #[arg(long, env = "RAYFARM_DEPTH", default_value_t = 3)]
    pub depth: u32,
}

/// Camera overrides; what is not given is the scene's.
#[derive(Args, Clone, Debug, Default)]
pub struct CameraArgs {
    /// Camera position X,Y,Z [default: the scene's camera].
    #[arg(long, env = "RAYFARM_EYE", value_parser = units::triple::<f32>, allow_negative_numbers = true)]
    pub eye: Option<[f32; 3]>,
    /// Point the camera looks at, X,Y,Z [default: the scene's].
    #[arg(long, env = "RAYFARM_LOOK_AT", value_parser = units::triple::<f32>, allow_negative_numbers = true)]
    pub look_at: Option<[f32; 3]>,
    /// Camera up direction, X,Y,Z, not along the view [default: the scene's].
    #[arg(long, env = "RAYFARM_UP", value_parser = parse_up, allow_negative_numbers = true)]
    pub up: Option<[f32; 3]>,
    /// Vertical field of view in degrees, in (0, 180) [default: the scene's].
    #[arg(long, env = "RAYFARM_FOV", value_parser = parse_fov)]
    pub fov: Option<f32>,
}

/// An up direction for clap: X,Y,Z, finite and not zero.
fn parse_up(s: &str) -> Result<[f32; 3], String> {
    let up = units::triple::<f32>(s)?;
    check_up(up)?;
    Ok(up)
}

/// A field of view for clap: degrees in (0, 180).
fn parse_fov(s: &str) -> Result<f32, String> {
    let fov: f32 = s.trim().parse().map_err(|e| format!("{s:?}: {e}"))?;
    check_fov(fov)?;
    Ok(fov)
}

impl CameraArgs {
    /// Whether any camera flag was given.
    fn any(&self) -> bool {
        self.eye.is_some() || self.look_at.is_some() || self.up.is_some() || self.fov.is_some()
    }

    /// `scene` with the given fields replaced, checked; `None` when no flag was given.
    pub fn over(&self, scene: &Camera) -> Result<Option<Camera>, String> {
        if !self.any() {
            return Ok(None);
        }
        let camera = Camera {
            eye: self.eye.unwrap_or(scene.eye),
            look_at: self.look_at.unwrap_or(scene.look_at),
            up: self.up.unwrap_or(scene.up),
            fov_y_degrees: self.fov.unwrap_or(scene.fov_y_degrees),
        };
        camera.check()?;
        Ok(Some(camera))
    }

    /// The camera of a job: only the given fields (the coordinator fills in the rest from the
    /// scene and checks the whole); `None` when no flag was given.
    pub fn to_proto(&self) -> Option<proto::Camera> {
        self.any().then(|| proto::Camera {
            eye: self.eye.map(Vec::from).unwrap_or_default(),
            look_at: self.look_at.map(Vec::from).unwrap_or_default(),
            up: self.up.map(Vec::from).unwrap_or_default(),
            // Zero means "the scene's" in the API; a given field of view is never zero.
            fov_y_degrees: self.fov.unwrap_or(0.0),
        })
    }
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct T {
        #[command(flatten)]
        camera: CameraArgs,
    }

    fn parse(args: &[&str]) -> Result<CameraArgs, String> {
        T::try_parse_from(std::iter::once("t").chain(args.iter().copied()))
            .map(|t| t.camera)
            .map_err(|e| e.to_string())
    }

    const SCENE: Camera = Camera {
        eye: [0.0, 0.0, 5.0],
        look_at: [0.0, 0.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_y_degrees: 40.0,
    };

    #[test]
    fn cameras_that_make_no_image_are_refused_as_flags_or_against_the_scene() {
        for (args, words) in [
            (&["--fov", "0"][..], "outside (0, 180)"),
            (&["--fov", "180"], "outside (0, 180)"),
            (&["--fov", "nan"], "outside (0, 180)"),
            (&["--up", "0,0,0"], "no direction"),
            (&["--up", "1,inf,0"], "finite"),
        ] {
            let e = parse(args).unwrap_err();
            assert!(e.contains(words), "{args:?}: {e}");
        }
        let along = parse(&["--up", "0,0,-1"]).unwrap();
        let e = along.over(&SCENE).unwrap_err();
        assert!(e.contains("along the view"), "{e}");
        let on_target = parse(&["--eye", "0,0,0"]).unwrap();
        assert!(on_target.over(&SCENE).unwrap_err().contains("distinct"));
    }

    #[test]
    fn given_fields_replace_the_scenes_and_only_they_are_sent() {
        let a = parse(&["--up", "1,0,0", "--fov", "30"]).unwrap();
        let c = a.over(&SCENE).unwrap().unwrap();
        assert_eq!(
            (c.eye, c.up, c.fov_y_degrees),
            (SCENE.eye, [1.0, 0.0, 0.0], 30.0)
        );
        let p = a.to_proto().unwrap();
        assert!(p.eye.is_empty() && p.look_at.is_empty());
        assert_eq!((p.up, p.fov_y_degrees), (vec![1.0, 0.0, 0.0], 30.0));
        assert_eq!(parse(&[]).unwrap().over(&SCENE).unwrap(), None);
        assert_eq!(parse(&[]).unwrap().to_proto(), None);
    }
}
