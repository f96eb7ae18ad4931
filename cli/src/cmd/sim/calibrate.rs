//! `rayfarm sim calibrate`: the cost model's prices measured on this machine, printed and
//! written to the file `rayfarm sim --cost` reads.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use rayfarm_node::job::parse_schedule;
use rayfarm_sim::calibrate::calibrate;
use rayfarm_sim::world::open_scene;

use super::ModelArgs;

/// Options of `rayfarm sim calibrate`.
#[derive(Args, Clone, Debug)]
pub struct CalibrateArgs {
    /// Scene directory whose passes are measured.
    #[arg(long)]
    pub scene: PathBuf,
    /// Workers of the measured simulation (their passes are the samples).
    #[arg(long, default_value_t = 4)]
    pub workers: usize,
    /// Schedule of the measured simulation.
    #[arg(long, default_value = "dynamic")]
    pub schedule: String,
    /// The calibration file to write.
    #[arg(long, default_value = "calibration.toml")]
    pub out: PathBuf,
    #[command(flatten)]
    pub model: ModelArgs,
}

/// `rayfarm sim calibrate`: measures, prints and writes the prices.
pub(super) fn run_calibrate(c: CalibrateArgs) -> anyhow::Result<()> {
    let schedule = parse_schedule(c.schedule.trim()).map_err(anyhow::Error::msg)?;
    let scene = open_scene(&c.scene)
        .map_err(anyhow::Error::msg)
        .with_context(|| format!("scene {}", c.scene.display()))?;
    let config = c.model.config(&c.scene, c.workers.max(1), schedule)?;
    let defaults = config.cost.compute;
    let cal = calibrate(&config, scene, defaults).map_err(anyhow::Error::msg)?;
    let p = &cal.cost;
    println!(
        "passes: {} without loads, {:.3} s of CPU; fit error {:.1}% (rms over the mean pass)",
        cal.passes,
        cal.pass_cpu.as_secs_f64(),
        cal.pass_fit_error * 100.0
    );
    println!(
        "  per pass {:.0} ns, radiance segment {:.1} ns, shadow segment {:.1} ns, camera sample \
         {:.1} ns, volume sample {:.1} ns{}",
        p.pass_ns,
        p.radiance_segment_ns,
        p.shadow_segment_ns,
        p.camera_sample_ns,
        p.volume_sample_ns,
        if p.volume_sample_ns == defaults.volume_sample_ns {
            " (not measured: kept from the cost model)"
        } else {
            ""
        }
    );
    for r in &cal.rounds {
        let planned = if r.whole {
            "every member (whole cluster)".to_string()
        } else {
            format!("{} dry", r.planned)
        };
        println!(
            "planning round, {} members x {} domains, {planned}: {:.3} ms",
            r.members,
            r.domains,
            r.ns / 1e6
        );
    }
    println!(
        "  incremental: {:.0} ns a round + {:.1} ns a member planned + {:.2} ns a member + {:.2} \
         ns a domain; fit error {:.1}%",
        p.round_ns,
        p.round_planned_ns,
        p.round_member_ns,
        p.round_domain_ns,
        cal.round_fit_error * 100.0
    );
    println!(
        "  whole cluster: {:.0} ns a round + {:.1} ns a member + {:.1} ns a domain; fit error \
         {:.1}%",
        p.whole_round_ns,
        p.whole_round_member_ns,
        p.whole_round_domain_ns,
        cal.whole_round_fit_error * 100.0
    );
    let text = format!(
        "# rayfarm sim calibrate --scene {} --workers {} --schedule {} {}\n# {} passes (fit \
         error {:.1}%), {} planning rounds (fit error {:.1}% incremental, {:.1}% whole \
         cluster)\n{}",
        c.scene.display(),
        c.workers,
        c.schedule,
        c.model.flags(),
        cal.passes,
        cal.pass_fit_error * 100.0,
        cal.rounds.len(),
        cal.round_fit_error * 100.0,
        cal.whole_round_fit_error * 100.0,
        p.to_toml()
    );
    std::fs::write(&c.out, text).with_context(|| format!("writing {}", c.out.display()))?;
    println!("wrote {}", c.out.display());
    Ok(())
}
