//! `rayfarm submit`: queue a frame on the cluster. Prints the job id at once, or with `--wait`
//! follows the job, saves the image and prints the statistics, like `render --local` does in
//! one process. `demo` reuses [`wait_and_save`].

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, anyhow};
use clap::Args;
use clap::builder::BoolishValueParser;
use rayfarm_core::progressive::Progressive;
use rayfarm_node::job::parse_schedule;
use rayfarm_node::proto;

use super::fetch::{check_writable, default_output, image_format, save_result};
use super::watch::{ReconnectArgs, ended_ok, follow, parse_stats, print_stats};
use crate::client::{Coordinator, CoordinatorArgs, runtime};
use crate::local_cluster::stop_signal;
use crate::view::{CameraArgs, FrameArgs};

/// Options of `rayfarm submit`.
#[derive(Args, Clone, Debug)]
pub struct SubmitArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorArgs,
    /// Scene name under the nodes' scene root, or an absolute path every node sees
    /// [default: the coordinator's default scene].
    #[arg(long, env = "RAYFARM_SCENE")]
    pub scene: Option<String>,
    #[command(flatten)]
    pub frame: FrameArgs,
    /// How rays are scheduled across workers: dynamic, image-plane, domain, hybrid or
    /// predictive.
    #[arg(long, env = "RAYFARM_SCHEDULE", default_value = "dynamic", value_parser = parse_schedule)]
    pub schedule: proto::Schedule,
    /// Higher runs first; equal priorities run in submission order.
    #[arg(
        long,
        env = "RAYFARM_PRIORITY",
        default_value_t = 0,
        allow_negative_numbers = true
    )]
    pub priority: i32,
    /// Drop every worker's cached domains before the frame, so it pays for every domain load
    /// (for comparing schedules; by default caches stay warm across frames of a scene).
    #[arg(long, env = "RAYFARM_COLD_CACHE", value_parser = BoolishValueParser::new())]
    pub cold_cache: bool,
    /// Render the samples in subframes, each a whole image committed (a preview after each):
    /// `doubling` (1, 1, 2, 4, ... samples) or a number of samples per subframe. The final
    /// image is the one-pass image to the bit [default: one pass].
    #[arg(long, env = "RAYFARM_PROGRESSIVE", value_parser = Progressive::parse)]
    pub progressive: Option<Progressive>,
    /// With --schedule predictive, how many domains ahead a new ray is copied: full (every
    /// domain along it), none (no copies: one domain at a time), ahead:N, predicted or
    /// predicted:P (as many as make the ray end among them with probability P, 0.9 by
    /// default; Park et al.). The image is the same whatever the setting [default: full].
    #[arg(long, env = "RAYFARM_SPECULATION")]
    pub speculation: Option<String>,
    /// With --schedule dynamic or predictive: each worker loads its next domains (the rest
    /// of its plan, then the coordinator's guess of the one it gets next) while it traces,
    /// when its cache has room beside the domains its plan needs. The image is the same.
    #[arg(long, env = "RAYFARM_PREFETCH", value_parser = BoolishValueParser::new())]
    pub prefetch: bool,
    /// A worker about to load a domain takes its bytes from a peer that has it loaded when
    /// that is cheaper than shared storage (by the storage and peer-link bandwidths measured
    /// or configured: `rayfarm-worker --peer-link-bandwidth`), checked like a file from
    /// storage, falling back to storage if the peer fails. Off by default: it pays where
    /// storage is slower than the workers' links and the schedule gives one domain to
    /// several workers (dynamic, predictive). The image is the same.
    #[arg(long, env = "RAYFARM_PEER_DOMAINS", value_parser = BoolishValueParser::new())]
    pub peer_domains: bool,
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Follow the job to its end, then save the image and print the statistics.
    #[arg(long, env = "RAYFARM_WAIT", value_parser = BoolishValueParser::new())]
    pub wait: bool,
    /// With --wait: output image, .png (8-bit sRGB) or .exr (linear float)
    /// [default: <job id>.png].
    #[arg(long, short, env = "RAYFARM_OUTPUT", requires = "wait")]
    pub output: Option<PathBuf>,
    /// With --wait: also write the frame's statistics as JSON here.
    #[arg(long, env = "RAYFARM_STATS_JSON", requires = "wait")]
    pub stats_json: Option<PathBuf>,
    /// With --wait: no progress bar and no statistics table.
    #[arg(long, env = "RAYFARM_QUIET", value_parser = BoolishValueParser::new())]
    pub quiet: bool,
    /// With --wait: how long to ride out a lost coordinator.
    #[command(flatten)]
    pub reconnect: ReconnectArgs,
}

impl SubmitArgs {
    /// The job the flags describe. A camera goes along only when a camera flag is given, and
    /// then only with the fields given: the coordinator fills the rest from the scene.
    pub fn job_spec(&self) -> proto::JobSpec {
        proto::JobSpec {
            scene: self.scene.clone().unwrap_or_default(),
            camera: self.camera.to_proto(),
            width: self.frame.width,
            height: self.frame.height,
            spp: self.frame.spp,
            max_depth: self.frame.depth,
            schedule: self.schedule as i32,
            priority: self.priority,
            cold_cache: self.cold_cache,
            progressive: self
                .progressive
                .and_then(Progressive::field)
                .map(|subframe_spp| proto::Progressive { subframe_spp }),
            speculation: self.speculation.clone().unwrap_or_default(),
            prefetch: self.prefetch,
            peer_domains: self.peer_domains,
        }
    }
}

/// What to do with a job's result once it has ended.
#[derive(Clone, Debug)]
pub struct WaitOptions {
    /// Image path; `None`: `<job id>.png`.
    pub output: Option<PathBuf>,
    /// Statistics JSON path.
    pub stats_json: Option<PathBuf>,
    /// No progress bar, no statistics table.
    pub quiet: bool,
    /// How long to keep reconnecting to a lost coordinator (zero: not at all).
    pub ride_out: Duration,
    /// The coordinator outlives this command: a result that could not be saved can be
    /// fetched again, and the error says how.
    pub fetch_again: bool,
}

pub fn run(a: SubmitArgs) -> anyhow::Result<()> {
    // Refuse a bad output name, or one that cannot be written, before the cluster spends a
    // frame on it.
    if let Some(out) = &a.output {
        image_format(out)?;
        check_writable(out)?;
    }
    if let Some(p) = &a.stats_json {
        check_writable(p)?;
    }
    let spec = a.job_spec();
    let wait = WaitOptions {
        output: a.output,
        stats_json: a.stats_json,
        quiet: a.quiet,
        ride_out: a.reconnect.ride_out()?,
        fetch_again: true,
    };
    runtime()?.block_on(async {
        let mut coord = a.coordinator.connect().await?;
        let job_id = coord.submit(spec).await.context("submitting the job")?;
        if !a.wait {
            println!("{job_id}");
            return Ok(());
        }
        if wait.output.is_none() {
            check_writable(&default_output(&job_id))?;
        }
        // The id first, so the job can be found again whatever happens to this command.
        println!("job {job_id}");
        let _ = std::io::Write::flush(&mut std::io::stdout());
        tokio::select! {
            r = wait_and_save(&mut coord, &job_id, &wait) => r.map(drop),
            signal = stop_signal() => {
                let signal = signal?;
                eprintln!();
                Err(anyhow!(
                    "interrupted by {signal}: stopped following job {job_id}, which goes on on \
                     the cluster; `rayfarm watch {job_id}` follows it again, `rayfarm cancel \
                     {job_id}` stops it, `rayfarm fetch {job_id} -o FILE` saves its image once \
                     it has succeeded"
                ))
            }
        }
    })
}

/// Follows job `job_id` to its end; if it succeeded, saves its image and statistics and prints
/// the statistics table (unless quiet) and `image hash: <hash>`. A failed or cancelled job is
/// an error. Returns where the image went.
pub async fn wait_and_save(
    coord: &mut Coordinator,
    job_id: &str,
    opts: &WaitOptions,
) -> anyhow::Result<PathBuf> {
    let output = opts
        .output
        .clone()
        .unwrap_or_else(|| default_output(job_id));
    let format = image_format(&output)?;
    let end = follow(coord, job_id, opts.quiet, opts.ride_out, None).await?;
    ended_ok(&end)?;
    let saved = save_result(
        coord,
        job_id,
        &output,
        format,
        opts.stats_json.as_deref(),
        opts.ride_out,
    )
    .await;
    let result = match saved {
        Err(e) if opts.fetch_again => {
            return Err(e.context(format!(
                "job {job_id} succeeded but its result was not saved; `rayfarm fetch {job_id} -o \
                 FILE` saves it"
            )));
        }
        r => r?,
    };
    if !opts.quiet {
        let stats = parse_stats(&result.stats_json)?;
        print_stats(&stats);
        println!("wrote {}", output.display());
    }
    println!("image hash: {}", result.image_hash);
    Ok(output)
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct T {
        #[command(flatten)]
        a: SubmitArgs,
    }

    fn parse(args: &[&str]) -> SubmitArgs {
        T::try_parse_from(std::iter::once("submit").chain(args.iter().copied()))
            .unwrap()
            .a
    }

    #[test]
    fn defaults_make_a_dynamic_640x480_job_on_the_default_scene_and_view() {
        let spec = parse(&[]).job_spec();
        assert_eq!(
            spec,
            proto::JobSpec {
                scene: String::new(),
                camera: None,
                width: 640,
                height: 480,
                spp: 4,
                max_depth: 3,
                schedule: proto::Schedule::Dynamic as i32,
                priority: 0,
                cold_cache: false,
                progressive: None,
                speculation: String::new(),
                prefetch: false,
                peer_domains: false,
            }
        );
        let doubling = parse(&["--progressive", "doubling"]).job_spec();
        assert_eq!(
            doubling.progressive,
            Some(proto::Progressive { subframe_spp: 0 })
        );
        let every = parse(&["--progressive", "2"]).job_spec();
        assert_eq!(
            every.progressive,
            Some(proto::Progressive { subframe_spp: 2 })
        );
        let bad = T::try_parse_from(["submit", "--progressive", "0"]);
        assert!(bad.is_err());
    }

    #[test]
    fn flags_become_the_job_and_only_given_camera_fields_are_sent() {
        let a = parse(&[
            "--scene",
            "nbody-10m",
            "--width",
            "96",
            "--height",
            "72",
            "--spp",
            "2",
            "--depth",
            "5",
            "--schedule",
            "image-plane",
            "--priority",
            "-3",
            "--eye",
            "0.5,-0.9,2",
        ]);
        let spec = a.job_spec();
        assert_eq!(spec.scene, "nbody-10m");
        assert_eq!(
            (spec.width, spec.height, spec.spp, spec.max_depth),
            (96, 72, 2, 5)
        );
        assert_eq!(spec.schedule(), proto::Schedule::ImagePlane);
        assert_eq!(spec.priority, -3);
        assert!(!spec.cold_cache);
        let cam = spec.camera.unwrap();
        assert_eq!(cam.eye, vec![0.5, -0.9, 2.0]);
        assert!(cam.look_at.is_empty() && cam.up.is_empty());
        assert_eq!(cam.fov_y_degrees, 0.0);

        assert!(parse(&["--cold-cache"]).job_spec().cold_cache);
        let cam = parse(&["--fov", "30"]).job_spec().camera.unwrap();
        assert_eq!(cam.fov_y_degrees, 30.0);
        assert!(cam.eye.is_empty());
    }

    #[test]
    fn bad_values_are_refused_by_the_parser() {
        let bad = |args: &[&str]| {
            T::try_parse_from(std::iter::once("submit").chain(args.iter().copied()))
                .err()
                .unwrap()
                .to_string()
        };
        assert!(bad(&["--schedule", "fastest"]).contains("known"));
        assert!(bad(&["--eye", "1,2"]).contains("X,Y,Z"));
        assert!(bad(&["--output", "f.png"]).contains("--wait"));
    }
}
