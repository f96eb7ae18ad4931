//! The deployment files parse and say what the README promises: the Kubernetes manifests
//! (no cluster here, so they are checked as documents), the compose file's services, and the
//! Slurm script's shell syntax.

use std::path::{Path, PathBuf};
use std::process::Command;

use yaml_rust2::{Yaml, YamlLoader};

fn deploy() -> PathBuf {
    rayfarm_tests::repo_root().join("deploy")
}

fn documents(path: &Path) -> Vec<Yaml> {
    let text = std::fs::read_to_string(path).expect("read yaml");
    YamlLoader::load_from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn str_at<'a>(doc: &'a Yaml, path: &[&str]) -> Option<&'a str> {
    path.iter()
        .try_fold(doc, |d, k| match &d[*k] {
            Yaml::BadValue => None,
            v => Some(v),
        })?
        .as_str()
}

#[test]
fn kubernetes_manifests_hold_the_promised_objects() {
    let mut objects = Vec::new();
    for entry in std::fs::read_dir(deploy().join("k8s")).expect("deploy/k8s") {
        let path = entry.expect("entry").path();
        for doc in documents(&path) {
            let kind = str_at(&doc, &["kind"])
                .expect("every object has a kind")
                .to_string();
            let name = str_at(&doc, &["metadata", "name"])
                .expect("and a name")
                .to_string();
            assert!(
                str_at(&doc, &["apiVersion"]).is_some(),
                "{kind} {name}: apiVersion"
            );
            objects.push((kind, name, doc));
        }
    }
    let find = |kind: &str, name: &str| {
        objects
            .iter()
            .find(|(k, n, _)| k == kind && n == name)
            .map(|(_, _, d)| d)
            .unwrap_or_else(|| panic!("no {kind} {name}"))
    };
    find("Deployment", "rayfarm-coordinator");
    find("Service", "rayfarm-coordinator");
    find("Job", "rayfarm-prepare");
    let headless = find("Service", "rayfarm-workers");
    assert_eq!(str_at(headless, &["spec", "clusterIP"]), Some("None"));
    let workers = find("StatefulSet", "rayfarm-worker");
    assert_eq!(
        str_at(workers, &["spec", "serviceName"]),
        Some("rayfarm-workers")
    );
    let scenes = find("PersistentVolumeClaim", "rayfarm-scenes");
    assert_eq!(
        scenes["spec"]["accessModes"][0].as_str(),
        Some("ReadWriteMany")
    );
    // Every pod runs the rayfarm image as a non-root user.
    for (kind, name, doc) in &objects {
        let pod = &doc["spec"]["template"]["spec"];
        if pod.is_badvalue() {
            continue;
        }
        assert_eq!(
            pod["securityContext"]["runAsNonRoot"].as_bool(),
            Some(true),
            "{kind} {name}"
        );
        let image = pod["containers"][0]["image"].as_str().unwrap_or_default();
        assert!(
            image.starts_with("rayfarm:"),
            "{kind} {name}: image {image}"
        );
    }
    // Peers reach workers through the headless service's per-pod names.
    let env = workers["spec"]["template"]["spec"]["containers"][0]["env"]
        .as_vec()
        .expect("worker env");
    let advertise = env
        .iter()
        .find(|e| e["name"].as_str() == Some("RAYFARM_ADVERTISE"))
        .and_then(|e| e["value"].as_str())
        .expect("RAYFARM_ADVERTISE");
    assert!(advertise.contains("rayfarm-workers"), "{advertise}");

    // Security is on: TLS to the coordinator, the Secrets mounted where the env points; the
    // user tokens reach the coordinator only.
    let coordinator = find("Deployment", "rayfarm-coordinator");
    assert_eq!(
        env_value(workers, "RAYFARM_COORDINATOR").map(|u| u.starts_with("https://")),
        Some(true)
    );
    // Mutual TLS: each pod presents the certificate named by the pod (its worker id), and
    // peers check it by the per-pod name they dial, not one shared name.
    assert_eq!(
        env_value(workers, "RAYFARM_TLS_CERT"),
        Some("/etc/rayfarm/nodes/node-$(POD_NAME).pem")
    );
    assert_eq!(env_value(workers, "RAYFARM_TLS_DOMAIN"), None);
    let secrets = |doc: &Yaml| -> Vec<String> {
        doc["spec"]["template"]["spec"]["volumes"]
            .as_vec()
            .expect("volumes")
            .iter()
            .filter_map(|v| v["secret"]["secretName"].as_str().map(String::from))
            .collect()
    };
    assert_eq!(
        secrets(coordinator),
        [
            "rayfarm-tls",
            "rayfarm-cluster-secret",
            "rayfarm-user-tokens"
        ]
    );
    // Workers hold their own certificates, not the coordinator's key.
    assert_eq!(
        secrets(workers),
        ["rayfarm-nodes", "rayfarm-cluster-secret"]
    );
    for (doc, vars) in [
        (
            coordinator,
            &[
                "RAYFARM_TLS_CERT",
                "RAYFARM_TLS_KEY",
                "RAYFARM_TLS_CLIENT_CA",
                "RAYFARM_CLUSTER_SECRET_FILE",
                "RAYFARM_USER_TOKENS_FILE",
            ][..],
        ),
        (
            workers,
            &[
                "RAYFARM_TLS_CERT",
                "RAYFARM_TLS_KEY",
                "RAYFARM_TLS_CA",
                "RAYFARM_TLS_CLIENT_CA",
                "RAYFARM_CLUSTER_SECRET_FILE",
            ][..],
        ),
    ] {
        let mounts = doc["spec"]["template"]["spec"]["containers"][0]["volumeMounts"]
            .as_vec()
            .expect("volumeMounts");
        for var in vars {
            let file = env_value(doc, var).unwrap_or_else(|| panic!("{var} is set"));
            assert!(
                mounts.iter().any(|m| m["mountPath"]
                    .as_str()
                    .is_some_and(|dir| file.starts_with(&format!("{dir}/")))),
                "{var}={file} is on no mounted volume"
            );
        }
    }
}

/// The value of environment variable `name` of a pod template's first container.
fn env_value<'a>(doc: &'a Yaml, name: &str) -> Option<&'a str> {
    doc["spec"]["template"]["spec"]["containers"][0]["env"]
        .as_vec()?
        .iter()
        .find(|e| e["name"].as_str() == Some(name))
        .and_then(|e| e["value"].as_str())
}

/// `map[key]`, or the value a YAML merge key (`<<: *anchor`) brings in, as compose reads it.
fn merged<'a>(map: &'a Yaml, key: &str) -> &'a Yaml {
    match &map[key] {
        Yaml::BadValue => match &map["<<"] {
            Yaml::BadValue => &map[key],
            base => merged(base, key),
        },
        found => found,
    }
}

#[test]
fn the_compose_file_has_prepare_coordinator_and_workers_with_certificates_of_their_own() {
    let docs = documents(&deploy().join("docker-compose.yml"));
    let services = &docs[0]["services"];
    for name in ["certs", "client-cert", "prepare", "coordinator"] {
        assert!(!services[name].is_badvalue(), "service {name}");
    }
    assert!(
        services["coordinator"]["ports"][0]
            .as_str()
            .is_some_and(|p| p.ends_with(":50051"))
    );
    assert!(!services["coordinator"]["healthcheck"].is_badvalue());
    assert_eq!(
        services["coordinator"]["depends_on"]["prepare"]["condition"].as_str(),
        Some("service_completed_successfully")
    );
    // Security is on: credentials from the one-shot `certs` services' volumes.
    assert_eq!(
        services["coordinator"]["depends_on"]["client-cert"]["condition"].as_str(),
        Some("service_completed_successfully")
    );
    let coordinator_env = &services["coordinator"]["environment"];
    for var in [
        "RAYFARM_TLS_CERT",
        "RAYFARM_TLS_KEY",
        "RAYFARM_TLS_CLIENT_CA",
        "RAYFARM_CLUSTER_SECRET_FILE",
        "RAYFARM_USER_TOKENS_FILE",
    ] {
        assert!(
            coordinator_env[var]
                .as_str()
                .is_some_and(|f| f.starts_with("/secrets/")),
            "coordinator {var}"
        );
    }
    // Every worker the certs service issues a certificate for is a service with its own
    // volume of credentials, its certificate's name as peer host, mutual TLS and a probe.
    let command: Vec<&str> = services["certs"]["command"]
        .as_vec()
        .expect("certs command")
        .iter()
        .filter_map(Yaml::as_str)
        .collect();
    let after = |flag: &str| {
        let at = command.iter().position(|a| *a == flag).expect(flag);
        command[at + 1]
    };
    assert_eq!(after("--node-dir"), "/nodes");
    let workers: Vec<&str> = after("--node").split(',').collect();
    assert!(workers.len() >= 2, "{workers:?}");
    for id in workers {
        let worker = &services[id];
        assert!(!worker.is_badvalue(), "service {id}");
        let volumes: Vec<&str> = worker["volumes"]
            .as_vec()
            .expect("volumes")
            .iter()
            .filter_map(Yaml::as_str)
            .collect();
        assert!(
            volumes.contains(&format!("node-{id}:/secrets:ro").as_str()),
            "{id}: {volumes:?}"
        );
        let certs_volumes = services["certs"]["volumes"].as_vec().expect("volumes");
        assert!(
            certs_volumes
                .iter()
                .any(|v| v.as_str() == Some(&format!("node-{id}:/nodes/{id}"))),
            "certs does not write {id}'s volume"
        );
        let env = &worker["environment"];
        assert_eq!(
            env["RAYFARM_ADVERTISE"].as_str(),
            Some(format!("{id}:7000").as_str())
        );
        assert!(
            merged(env, "RAYFARM_COORDINATOR")
                .as_str()
                .is_some_and(|u| u.starts_with("https://"))
        );
        assert_eq!(
            merged(env, "RAYFARM_TLS_CLIENT_CA").as_str(),
            Some("/secrets/ca.pem")
        );
        // Peers check each other by their own names, not one shared name.
        assert!(merged(env, "RAYFARM_TLS_DOMAIN").is_badvalue());
        assert!(!worker["healthcheck"].is_badvalue(), "{id}");
        assert!(!merged(worker, "entrypoint").is_badvalue(), "{id}");
    }
}

#[test]
fn the_slurm_script_is_valid_shell() {
    let script = deploy().join("slurm/rayfarm.sbatch");
    let out = Command::new("bash")
        .arg("-n")
        .arg(&script)
        .output()
        .expect("bash -n");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
