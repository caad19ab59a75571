//! The output contract: every message a replay (`--out`) and a live session (`--record`)
//! write validates against the JSON Schema its channel carries, the schemas are the ones
//! generated from the Rust types, and replay and live share one schema per topic.

mod common;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::time::Duration;

use common::live::{acquire, finish, prefix, report, spawn_live};
use common::{ok, repo};
use jointid::io::contract::{CONTRACT_VERSION, topic_schema};

/// Validates every output message of `path` against its channel's schema; returns the
/// message count per topic and the schema (name, body) per topic.
fn validate_outputs(
    path: &Path,
) -> (
    BTreeMap<String, usize>,
    BTreeMap<String, (String, serde_json::Value)>,
) {
    let bytes = std::fs::read(path).unwrap();
    let mut counts = BTreeMap::new();
    let mut schemas = BTreeMap::new();
    let mut validators = BTreeMap::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        let topic = m.channel.topic.clone();
        if topic == "/jointid/excitation" || topic == "/jointid/response" {
            continue;
        }
        let schema = m
            .channel
            .schema
            .as_ref()
            .expect("output topics carry a schema");
        assert_eq!(schema.encoding, "jsonschema", "{topic}");
        let body: serde_json::Value = serde_json::from_slice(&schema.data).unwrap();
        let (name, expected) =
            topic_schema(&topic).unwrap_or_else(|| panic!("{topic} is not in the contract"));
        assert_eq!(schema.name, name, "{topic}");
        assert_eq!(
            &body, expected,
            "{topic}: the recording's schema is the generated one"
        );
        schemas.insert(topic.clone(), (schema.name.clone(), body.clone()));
        let validator = validators
            .entry(topic.clone())
            .or_insert_with(|| jsonschema::validator_for(&body).unwrap());
        let msg: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
        let errors: Vec<String> = validator
            .iter_errors(&msg)
            .map(|e| format!("{e} at {}", e.instance_path()))
            .collect();
        assert!(errors.is_empty(), "{topic}: {errors:?}\n{msg}");
        if topic != "/jointid/log" {
            assert_eq!(msg["version"], CONTRACT_VERSION, "{topic}");
        }
        *counts.entry(topic).or_insert(0) += 1;
    }
    (counts, schemas)
}

#[test]
fn replay_and_live_outputs_validate_against_one_schema_per_topic() {
    let dir = tempfile::tempdir().unwrap();
    let setup = repo("recordings/two-beam-friction.toml");
    let sim = dir.path().join("sim.mcap");
    ok(&[
        "simulate",
        setup.to_str().unwrap(),
        "--out",
        sim.to_str().unwrap(),
        "--scenario",
        "random",
        "--steps",
        "600",
        "--noise",
        "additive:0.01",
        "--seed",
        "2",
    ]);
    let out = dir.path().join("replay-out.mcap");
    let v: serde_json::Value = serde_json::from_str(&ok(&[
        "replay",
        sim.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]))
    .unwrap();
    assert_eq!(v["version"], CONTRACT_VERSION);
    let (counts, replay_schemas) = validate_outputs(&out);
    for topic in [
        "/jointid/residuals",
        "/jointid/states",
        "/jointid/predicted",
        "/jointid/parameters",
        "/jointid/diagnostics",
        "/jointid/log",
    ] {
        assert!(
            counts.get(topic).copied().unwrap_or(0) > 0,
            "{topic}: {counts:?}"
        );
    }
    assert_eq!(counts["/jointid/predicted"], 600);

    // A live session of the same setup.
    let p = prefix("contract");
    let rec = dir.path().join("live.mcap");
    let live = spawn_live(
        &p,
        &["--record", rec.to_str().unwrap(), "--refit-every", "500"],
    );
    let acq = acquire(&p, &["--samples", "3000", "--seed", "4"])
        .output()
        .unwrap();
    assert!(
        acq.status.success(),
        "{}",
        String::from_utf8_lossy(&acq.stderr)
    );
    let r = report(&finish(live, Duration::from_secs(120)));
    assert_eq!(r["version"], CONTRACT_VERSION);
    let live_params = r["parameters"].as_array().unwrap();
    let replay_params = v["parameters"].as_array().unwrap();
    let keys = |ps: &Vec<serde_json::Value>| -> BTreeSet<String> {
        ps.iter()
            .flat_map(|p| p.as_object().unwrap().keys().cloned())
            .collect()
    };
    assert_eq!(
        keys(live_params),
        keys(replay_params),
        "live and replay --json parameters share one shape"
    );
    let (live_counts, live_schemas) = validate_outputs(&rec);
    assert!(live_counts["/jointid/parameters"] > 0 && live_counts["/jointid/residuals"] > 0);
    for (topic, schema) in &live_schemas {
        if let Some(replay) = replay_schemas.get(topic) {
            assert_eq!(schema, replay, "{topic}: replay and live write one schema");
        }
    }
}
