//! Replay through the pipeline stages gives the numbers of the batch path that existed
//! before the pipeline (read every frame, `align`, `identify`), bit for bit, on the
//! shipped recordings; and a damaged input keeps the replay policy.

use std::path::{Path, PathBuf};

use jointid::align::align;
use jointid::app::{self, ReplayRequest, excitation_channels, response_channels};
use jointid::identify::{IdentifyOptions, identify};
use jointid::io::mcap::{InputTopic, stream_frames};
use jointid::setup::Setup;

fn recording(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("recordings")
        .join(name)
}

/// The pre-pipeline replay: whole lists, `align`, `identify`.
fn batch_parameters(path: &Path, passes: usize) -> (usize, Vec<(f64, f64)>) {
    let mut stream = stream_frames(path).unwrap();
    let setup = Setup::from_toml(stream.header.setup_toml.as_ref().unwrap(), "attached").unwrap();
    let (mut e, mut r) = (Vec::new(), Vec::new());
    for item in stream.by_ref() {
        match item.unwrap() {
            (InputTopic::Excitation, f) => e.push(f),
            (InputTopic::Response, f) => r.push(f),
        }
    }
    let (data, err) = align(
        &e,
        &r,
        excitation_channels(&setup).names.len(),
        response_channels(&setup).names.len(),
        setup.dt_s,
    );
    assert!(err.is_none(), "{err:?}");
    let mut opts = IdentifyOptions::from_setup(&setup);
    opts.passes = passes;
    let id = identify(&setup, &data, &opts, None, &mut |_| {}, &mut |_, _| {}).unwrap();
    let p = id
        .final_parameters()
        .unwrap()
        .iter()
        .map(|p| (p.value, p.std_error))
        .collect();
    (data.len(), p)
}

#[test]
fn pipeline_replay_equals_the_batch_identification() {
    for name in ["two-beam-friction.mcap", "two-beam-spring-sine.mcap"] {
        let path = recording(name);
        let passes = 2;
        let (n, want) = batch_parameters(&path, passes);
        let req = ReplayRequest {
            recording: path.clone(),
            passes: Some(passes),
            ..ReplayRequest::default()
        };
        let mut progress_starts = 0;
        let got = app::replay(&req, &mut |p| {
            if let app::Progress::Start { samples, .. } = p {
                assert_eq!(samples, n);
                progress_starts += 1;
            }
        })
        .unwrap();
        assert_eq!(progress_starts, 1);
        assert_eq!(got.samples, n);
        assert_eq!(got.identification.passes.len(), passes);
        let got: Vec<(f64, f64)> = got
            .identification
            .final_parameters()
            .unwrap()
            .iter()
            .map(|p| (p.value, p.std_error))
            .collect();
        // Same code over the same data: identical, not merely close.
        assert_eq!(got, want, "{name}");
    }
}

#[test]
fn pipeline_replay_keeps_the_samples_before_a_bad_one() {
    // The shipped recording rewritten without sample 700: a gap.
    let src = recording("two-beam-friction.mcap");
    let mut stream = stream_frames(&src).unwrap();
    let header = stream.header.clone();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("gap.mcap");
    let mut w =
        jointid::io::mcap::RecordingWriter::create(&out, jointid::io::FrameEncoding::Binary)
            .unwrap();
    w.attach_setup(header.setup_toml.as_ref().unwrap()).unwrap();
    w.declare_inputs(&header.excitation_channels, &header.response_channels)
        .unwrap();
    for item in stream.by_ref() {
        let (topic, f) = item.unwrap();
        if f.sample == 700 {
            continue; // indices jump 699 -> 701: a gap
        }
        w.write_frame(topic, &f).unwrap();
    }
    w.finish().unwrap();
    let req = ReplayRequest {
        recording: out.clone(),
        passes: Some(1),
        ..ReplayRequest::default()
    };
    let o = app::replay(&req, &mut |_| {}).unwrap();
    assert_eq!(o.samples, 700, "samples 0..=699 are kept");
    // A gap ends the first segment (lost frames or a restarted acquisition in a live
    // recording): a warning, not an error.
    assert!(o.input_error.is_none(), "{:?}", o.input_error);
    let w = o.input_warnings.join("\n");
    assert!(
        w.contains("699 is followed by 701") && w.contains("first segment"),
        "{w}"
    );
}
