//! `rayfarm sim calibrate`: the cost model's prices measured on this machine, printed and
//! written to the file `rayfarm sim --cost` reads.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use rayfarm_node::job::parse_schedule;
use rayfarm_sim::calibrate::calibrate;
use rayfarm_sim::world::open_scene;

use super::{ModelArgs, transport};

/// Options of `rayfarm sim calibrate`.
#[derive(Args, Clone, Debug)]
pub struct CalibrateArgs {
    /// Scene directory whose passes are measured.
    #[arg(long)]
    pub scene: PathBuf,
    /// Workers of the measured simulation (their passes are the samples).
    #[arg(long, default_value_t = 4)]
    pub workers: usize,
    /// Schedule of the measured simulation; several, separated by commas, run one job each
    /// on the same workers and all their passes are measured (e.g. dynamic,predictive, so
    /// speculative copies and verdicts are priced too).
    #[arg(long, default_value = "dynamic")]
    pub schedule: String,
    /// The calibration file to write.
    #[arg(long, default_value = "calibration.toml")]
    pub out: PathBuf,
    #[command(flatten)]
    pub model: ModelArgs,
}

/// Fits `ns = bundle + byte x bytes` to the transport's timings: coefficients and error.
fn fit_transport(samples: &[transport::TransportSample]) -> ([f64; 2], f64) {
    if samples.len() < 2 {
        return ([0.0; 2], 0.0);
    }
    let (c, e) = rayfarm_sim::calibrate::fit(
        &samples
            .iter()
            .map(|t| (vec![1.0, t.bytes as f64], t.ns))
            .collect::<Vec<_>>(),
    );
    ([c[0], c[1]], e)
}

/// `rayfarm sim calibrate`: measures, prints and writes the prices.
pub(super) fn run_calibrate(c: CalibrateArgs) -> anyhow::Result<()> {
    let mut schedules = c
        .schedule
        .split(',')
        .map(|s| parse_schedule(s.trim()).map_err(anyhow::Error::msg))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let schedule = schedules.pop().context("no schedule")?;
    let scene = open_scene(&c.scene)
        .map_err(anyhow::Error::msg)
        .with_context(|| format!("scene {}", c.scene.display()))?;
    let mut config = c.model.config(&c.scene, c.workers.max(1), schedule)?;
    config.warm_up = schedules;
    let defaults = config.cost.compute;
    let mut cal = calibrate(&config, scene, defaults).map_err(anyhow::Error::msg)?;
    // Peer bundles: the sender's encoding and the receiver's decoding and handling timed in
    // the run, the gRPC stream between them over loopback; its cost split evenly between the
    // two ends.
    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
    let transport = if cal.bundles.len() >= 2 {
        transport::measure(&cal.bundles, threads)?
    } else {
        Vec::new()
    };
    let transport_fit = fit_transport(&transport);
    let (send, receive, (tr, tr_err)) = (cal.encode.0, cal.receive.0, transport_fit);
    cal.cost.bundle_send_ns = send[0] + tr[0] / 2.0;
    cal.cost.bundle_send_byte_ns = send[1] + tr[1] / 2.0;
    cal.cost.bundle_receive_ns = receive[0] + tr[0] / 2.0;
    cal.cost.bundle_receive_byte_ns = receive[1] + tr[1] / 2.0;
    cal.cost.check().map_err(anyhow::Error::msg)?;
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
    for r in &cal.reports {
        println!(
            "queue report taken in, no round after it, {} members x {} domains: {:.1} us",
            r.members,
            r.domains,
            r.ns / 1e3
        );
    }
    println!(
        "  {:.0} ns a report (the median; a round's reports are priced so, the rest of it below)",
        p.report_ns
    );
    for r in &cal.rounds {
        let planned = if r.whole {
            "every member (whole cluster)".to_string()
        } else {
            format!("{} dry, reports naming {} queues", r.planned, r.queues)
        };
        println!(
            "planning round, {} members x {} domains, {planned}: {:.3} ms",
            r.members,
            r.domains,
            r.ns / 1e6
        );
    }
    println!(
        "  incremental: {:.0} ns a round + ({:.1} ns + {:.3} ns a domain) a member planned + {:.1} \
         ns a queue a report names + {:.2} ns a member + {:.2} ns a domain; fit error {:.1}%",
        p.round_ns,
        p.round_planned_ns,
        p.round_planned_domain_ns,
        p.round_queue_ns,
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
    for f in &cal.flushes {
        println!(
            "holders flush, {} members x {} domains every {} ms: {} told, {} lines made: {:.3} ms",
            f.members,
            f.domains,
            f.interval.as_millis(),
            f.told,
            f.lines,
            f.ns / 1e6
        );
    }
    println!(
        "  {:.0} ns a flush + {:.1} ns a member + {:.1} ns a line made; fit error {:.1}% (rms of relative errors)",
        p.flush_ns,
        p.flush_member_ns,
        p.flush_line_ns,
        cal.flush_fit_error * 100.0
    );
    println!(
        "peer bundles: {} received; receiving (decode, machine) {:.0} ns + {:.3} ns a byte, fit \
         error {:.1}%; encoding {:.0} ns + {:.3} ns a byte over {} bundles, fit error {:.1}%",
        cal.bundles_received,
        cal.receive.0[0],
        cal.receive.0[1],
        cal.receive.1 * 100.0,
        cal.encode.0[0],
        cal.encode.0[1],
        cal.bundles.len(),
        cal.encode.1 * 100.0
    );
    for t in &transport {
        println!(
            "gRPC loopback, {} bytes a bundle, {} sends: {:.1} us a bundle (both ends, process \
             CPU)",
            t.bytes,
            t.sends,
            t.ns / 1e3
        );
    }
    println!(
        "  transport {:.0} ns + {:.3} ns a byte, fit error {:.1}%; priced: sending {:.0} ns + \
         {:.3} ns a byte, receiving {:.0} ns + {:.3} ns a byte",
        tr[0],
        tr[1],
        tr_err * 100.0,
        p.bundle_send_ns,
        p.bundle_send_byte_ns,
        p.bundle_receive_ns,
        p.bundle_receive_byte_ns
    );
    println!(
        "finished passes taken in: {} ({:.0} ns a pass + {:.1} ns a ray sent on + {:.1} ns a \
         domain along a born ray + {:.1} ns a verdict), fit error {:.1}%",
        cal.finished,
        p.finished_pass_ns,
        p.finished_ray_ns,
        p.finished_path_domain_ns,
        p.finished_verdict_ns,
        cal.finished_fit_error * 100.0
    );
    let text = format!(
        "# rayfarm sim calibrate --scene {} --workers {} --schedule {} {}\n# {} passes (fit \
         error {:.1}%), {} planning rounds (fit error {:.1}% incremental, {:.1}% whole \
         cluster), {} holders flushes (fit error {:.1}%)\n# {} bundles received (receiving fit error {:.1}%, encoding {:.1}%, gRPC \
         transport {:.1}%)\n# {} finished passes taken in (fit error {:.1}%)\n{}",
        c.scene.display(),
        c.workers,
        c.schedule,
        c.model.flags(),
        cal.passes,
        cal.pass_fit_error * 100.0,
        cal.rounds.len(),
        cal.round_fit_error * 100.0,
        cal.whole_round_fit_error * 100.0,
        cal.flushes.len(),
        cal.flush_fit_error * 100.0,
        cal.bundles_received,
        cal.receive.1 * 100.0,
        cal.encode.1 * 100.0,
        tr_err * 100.0,
        cal.finished,
        cal.finished_fit_error * 100.0,
        p.to_toml()
    );
    std::fs::write(&c.out, text).with_context(|| format!("writing {}", c.out.display()))?;
    println!("wrote {}", c.out.display());
    Ok(())
}
