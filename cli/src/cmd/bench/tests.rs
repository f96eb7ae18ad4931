use clap::Parser;

use std::path::Path;

use super::plan::writable_parent;
use super::*;

#[derive(Parser)]
struct T {
    #[command(flatten)]
    a: BenchArgs,
}

fn parse(args: &[&str]) -> Result<BenchArgs, String> {
    T::try_parse_from(
        ["bench", "--scene", "/s/nbody"]
            .into_iter()
            .chain(args.iter().copied()),
    )
    .map(|t| t.a)
    .map_err(|e| e.to_string())
}

#[test]
fn defaults_compare_four_schedules_three_times_at_512() {
    let a = parse(&[]).unwrap();
    assert_eq!(
        a.schedules,
        [
            proto::Schedule::Dynamic,
            proto::Schedule::Predictive,
            proto::Schedule::ImagePlane,
            proto::Schedule::Domain
        ]
        .map(|s| (s, String::new()))
    );
    assert_eq!(
        (a.workers, a.repeats, a.width, a.height, a.spp, a.depth),
        (4, 3, 512, 512, 4, 3)
    );
    assert!(a.cache_bytes.is_none() && a.threads.is_none() && a.coordinator.is_none());
    assert!(coordinator_extra(&a).is_empty() && worker_extra(&a).is_empty());
    assert!(a.progressive.is_none());
    let p = parse(&["--progressive", "doubling"]).unwrap();
    assert_eq!(p.progressive, Some(Progressive::Doubling));
    assert!(parse(&["--progressive", "none"]).is_err());
}

#[test]
fn storage_and_replication_flags_are_passed_through_only_when_given() {
    let a = parse(&[
        "--storage-bandwidth",
        "100MiB/s",
        "--storage-latency",
        "5ms",
        "--replicate",
        "none",
        "--cache-bytes",
        "8MiB",
        "--schedules",
        "domain,dynamic,predictive:predicted",
    ])
    .unwrap();
    assert_eq!(
        worker_extra(&a),
        [
            "--storage-bandwidth",
            "100MiB/s",
            "--storage-latency",
            "5ms"
        ]
        .map(std::ffi::OsString::from)
    );
    assert_eq!(
        coordinator_extra(&a),
        ["--replicate", "none"].map(std::ffi::OsString::from)
    );
    assert_eq!(a.cache_bytes, Some(8 << 20));
    assert_eq!(
        a.schedules,
        [
            (proto::Schedule::Domain, ""),
            (proto::Schedule::Dynamic, ""),
            (proto::Schedule::Predictive, "predicted")
        ]
        .map(|(s, setting)| (s, setting.to_string()))
    );
}

#[test]
fn rates_take_units_and_an_optional_per_second() {
    assert_eq!(
        parse_rate("100MiB/s"),
        Ok(Rate {
            text: "100MiB/s".into(),
            bytes_per_second: 100 << 20
        })
    );
    assert_eq!(parse_rate("1GiB").unwrap().bytes_per_second, 1 << 30);
    assert!(parse_rate("fast").unwrap_err().contains("100MiB/s"));
    assert!(parse_rate("0/s").unwrap_err().contains("more than zero"));
}

#[test]
fn bad_values_are_refused_by_the_parser() {
    assert!(
        parse(&["--schedules", "fastest"])
            .unwrap_err()
            .contains("known")
    );
    assert!(parse(&["--schedules", "dynamic:full"]).is_err());
    assert!(parse(&["--repeats", "0"]).is_err());
    assert!(parse(&["--replicate", "all"]).is_err());
}

#[test]
fn a_plan_refuses_repeated_schedules_missing_scenes_and_non_png_charts() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("nothing");
    let a = parse(&["--schedules", "dynamic,dynamic"]).unwrap();
    let err = Plan::new(&BenchArgs {
        scene: scene.clone(),
        ..a
    })
    .err()
    .unwrap()
    .to_string();
    assert!(err.contains("twice"), "{err}");
    let a = parse(&[]).unwrap();
    let err = format!(
        "{:#}",
        Plan::new(&BenchArgs {
            scene: scene.clone(),
            ..a
        })
        .err()
        .unwrap()
    );
    assert!(err.contains("not a usable prepared scene"), "{err}");
    let a = parse(&["--csv", "out.csv", "--chart", "chart.jpg"]).unwrap();
    let err = Plan::new(&BenchArgs { scene, ..a })
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("name it .png"), "{err}");
}

#[test]
fn output_directories_are_made_up_front() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("a/b/out.csv");
    writable_parent(&out).unwrap();
    assert!(tmp.path().join("a/b").is_dir());
    assert!(writable_parent(Path::new("out.csv")).is_ok());
    let blocker = tmp.path().join("file");
    std::fs::write(&blocker, b"").unwrap();
    let err = format!(
        "{:#}",
        writable_parent(&blocker.join("out.csv")).unwrap_err()
    );
    assert!(err.contains("creating"), "{err}");
}
