//! Tracking: connection parameters as they change during a test (a bolt loosening, a joint
//! wearing in), from the same per-sample estimates that feed the batch fit.
//!
//! Design (decided here, stated in docs/DESIGN.md): the batch fit of a pass stays the
//! whole-record least-squares fit with its standard errors, because that is what the
//! passes, the stopping rule and the uncertainty are about. Beside it, a [`Tracker`] keeps a
//! second fit per connection with exponential forgetting `λ` per sample (memory
//! `N = 1/(1 − λ)` samples, time constant `τ = dt/(1 − λ)`) and solves it every
//! `every` samples, giving a time history of the parameters with standard errors computed
//! from the discounted rows. With `λ = 1` the history is the growing-window estimate, i.e.
//! what the online refit would have published at that moment.
//!
//! How fast a change is followed: after a step change in a parameter the discounted fit
//! weighs the old regime by `λ^k` after `k` samples, so its estimate reaches the new value
//! to within a fraction `ε` of the step after about `N·ln(1/ε)` samples (≈ 3 N for 5 %) when
//! the regressors are stationary. The cost is variance: the standard error grows like
//! `√(N_total/N)` against the batch fit.
//!
//! A fit that cannot be solved yet (too few rows after a stuck interval, rank deficiency
//! early in the record) is recorded as a point without values and the reason, never as a
//! number.

use serde::Serialize;

use crate::estimate::StepOutput;
use crate::identify::ParameterAccumulator;
use crate::setup::Setup;

/// What to track.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackOptions {
    /// Forgetting factor per sample, `0 < λ ≤ 1`.
    pub forgetting: f64,
    /// Solve and record every this many samples (≥ 1).
    pub every: usize,
    /// Largest acceptable condition number of a tracked fit.
    pub max_condition: f64,
}

impl TrackOptions {
    /// Default interval: a quarter of the memory (`N/4`, at least 1) when forgetting, else
    /// a twentieth of the record.
    pub fn default_every(forgetting: f64, samples: usize) -> usize {
        if forgetting < 1.0 {
            ((0.25 / (1.0 - forgetting)).round() as usize).max(1)
        } else {
            (samples / 20).max(1)
        }
    }

    /// Memory of the forgetting, samples (`∞` without forgetting).
    pub fn memory_samples(&self) -> f64 {
        if self.forgetting < 1.0 {
            1.0 / (1.0 - self.forgetting)
        } else {
            f64::INFINITY
        }
    }
}

/// One tracked parameter value.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrackedValue {
    pub value: f64,
    pub std_error: f64,
}

/// The tracked parameters at one sample; `values[c]` is `None` (with `unsolved[c]` saying
/// why) when connection `c`'s fit could not be solved there.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrackPoint {
    pub sample: u64,
    /// One entry per parameter, in setup order; `None` where the connection's fit failed.
    pub parameters: Vec<Option<TrackedValue>>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub unsolved: Vec<String>,
}

/// The history of one pass, with the settings that produced it.
#[derive(Debug, Clone, Serialize)]
pub struct Track {
    pub forgetting: f64,
    pub memory_samples: f64,
    pub every: usize,
    pub points: Vec<TrackPoint>,
}

/// Discounted online fit, solved periodically.
pub struct Tracker {
    acc: ParameterAccumulator,
    opts: TrackOptions,
    blocks: Vec<usize>,
    names: Vec<String>,
    seen: usize,
    points: Vec<TrackPoint>,
}

impl Tracker {
    pub fn new(setup: &Setup, stick_band: f64, opts: TrackOptions) -> Self {
        Self {
            acc: ParameterAccumulator::new(setup, stick_band, opts.forgetting),
            opts: TrackOptions {
                every: opts.every.max(1),
                ..opts
            },
            blocks: setup.connections.iter().map(|c| c.basis.len()).collect(),
            names: setup.connections.iter().map(|c| c.name.clone()).collect(),
            seen: 0,
            points: Vec::new(),
        }
    }

    /// The stuck band of the tracked fit follows the batch fit's (see
    /// [`ParameterAccumulator::widen_band`]).
    pub fn widen_band(&mut self, c: usize, d: f64, v: f64) {
        self.acc.widen_band(c, d, v);
    }

    /// Add one sample's estimate; every `every` samples, solve and record.
    pub fn push(&mut self, out: &StepOutput) {
        self.acc.push(out);
        self.seen += 1;
        if self.seen.is_multiple_of(self.opts.every) {
            self.record(None, out.sample);
        }
    }

    /// Whether this tracker keeps no memory limit (forgetting 1): its fit is then, row for
    /// row, the batch fit `ParameterAccumulator::new(setup, stick_band, 1.0)` with the same
    /// stuck bands, and it can [`follow`](Self::follow) that fit instead of accumulating
    /// every row a second time.
    pub fn follows_batch(&self) -> bool {
        self.opts.forgetting == 1.0
    }

    /// [`push`](Self::push) for a tracker that [`follows_batch`](Self::follows_batch):
    /// `batch` (the same stick band and widening) has just taken sample `sample`; every
    /// `every` samples its running fit is solved and recorded. The same track, bit for bit,
    /// as pushing; why: the second accumulation was an eighth of a Kalman pass
    /// (BENCHMARKS.md, thirty-fifth session).
    pub fn follow(&mut self, batch: &ParameterAccumulator, sample: u64) {
        self.seen += 1;
        if self.seen.is_multiple_of(self.opts.every) {
            self.record(Some(batch), sample);
        }
    }

    /// Solve the tracked fit (`batch`'s when following it) and record it at `sample`.
    fn record(&mut self, batch: Option<&ParameterAccumulator>, sample: u64) {
        let mut parameters = Vec::with_capacity(self.blocks.iter().sum());
        let mut unsolved = Vec::new();
        let fits = batch.unwrap_or(&self.acc).solve(self.opts.max_condition);
        for (c, fit) in fits.into_iter().enumerate() {
            match fit {
                Ok(f) => parameters.extend(f.values.iter().zip(&f.std_errors).map(|(&v, &s)| {
                    Some(TrackedValue {
                        value: v,
                        std_error: s,
                    })
                })),
                Err(e) => {
                    parameters.extend(std::iter::repeat_n(None, self.blocks[c]));
                    unsolved.push(format!("{}: {e}", self.names[c]));
                }
            }
        }
        self.points.push(TrackPoint {
            sample,
            parameters,
            unsolved,
        });
    }

    /// The history; the last sample is recorded too if the interval did not end on it.
    pub fn finish(self, last_sample: Option<u64>) -> Track {
        self.finish_following(None, last_sample)
    }

    /// [`finish`](Self::finish) for a tracker that followed `batch` (`None`: it pushed).
    pub fn finish_following(
        mut self,
        batch: Option<&ParameterAccumulator>,
        last_sample: Option<u64>,
    ) -> Track {
        if let Some(s) = last_sample
            && self.points.last().is_none_or(|p| p.sample != s)
            && self.seen > 0
        {
            self.record(batch, s);
        }
        Track {
            forgetting: self.opts.forgetting,
            memory_samples: self.opts.memory_samples(),
            every: self.opts.every,
            points: self.points,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DVector;

    fn spring_setup() -> Setup {
        setup_with_basis(r#"["u"]"#)
    }

    fn setup_with_basis(basis: &str) -> Setup {
        let text = r#"
[model]
nodes = [{ id = 1, x = 0.0 }, { id = 2, x = 1.0 }]
beams = [{ name = "A", from = 1, to = 2, elements = 1, ei = 1.0e3, mass_per_length = 1.0 }]
supports = [{ node = 1, fix = ["w", "rz"] }]

[[excitation]]
name = "tip.force"
dof = { node = 2, dir = "w" }

[[sensors]]
name = "tip.disp"
dof = { node = 2, dir = "w" }
quantity = "displacement"

[[connections]]
name = "joint"
dof = { node = 2, dir = "w" }
basis = BASIS

[integrator]
dt_s = 1.0e-3
"#;
        Setup::from_toml(&text.replace("BASIS", basis), "inline").expect("valid setup")
    }

    fn out(sample: u64, d: f64, f: f64) -> StepOutput {
        let mut o = StepOutput::new(1);
        o.sample = sample;
        o.delta = DVector::from_element(1, d);
        o.force = DVector::from_element(1, f);
        o
    }

    /// A stiffness that drops from 100 to 70 at sample 1000 is followed: with memory 50
    /// samples the estimate is within 1 % of 70 by 5 memories after the drop, and the
    /// growing-window estimate (λ = 1) is not.
    #[test]
    fn forgetting_follows_a_stiffness_drop_and_the_growing_window_does_not() {
        let setup = spring_setup();
        let run = |forgetting: f64| {
            let mut t = Tracker::new(
                &setup,
                1e-6,
                TrackOptions {
                    forgetting,
                    every: 10,
                    max_condition: 1e12,
                },
            );
            for i in 1..=2000u64 {
                let d = (i as f64 * 0.37).sin() * 1e-3;
                let k = if i <= 1000 { 100.0 } else { 70.0 };
                t.push(&out(i, d, k * d));
            }
            t.finish(Some(2000))
        };
        let at = |track: &Track, s: u64| -> f64 {
            let p = track.points.iter().find(|p| p.sample == s).expect("point");
            p.parameters[0].as_ref().expect("solved").value
        };
        let tracked = run(1.0 - 1.0 / 50.0);
        assert_eq!(tracked.every, 10);
        assert!((tracked.memory_samples - 50.0).abs() < 1e-9);
        assert!((at(&tracked, 1000) - 100.0).abs() < 1e-6);
        assert!((at(&tracked, 1250) - 70.0).abs() < 0.7);
        assert!((at(&tracked, 2000) - 70.0).abs() < 1e-6);
        let growing = run(1.0);
        assert!((at(&growing, 2000) - 85.0).abs() < 2.0);
    }

    /// Without forgetting, a tracker that follows the batch accumulator (with the same stick
    /// band and widening, as a Kalman pass sets them; a friction term, so samples are
    /// excluded as stuck) records the same track, to the bit, as
    /// one that accumulates every row itself — also when the last sample is off the
    /// interval; with forgetting it does not offer to follow.
    #[test]
    fn a_tracker_following_the_batch_fit_records_the_pushed_track() {
        use crate::identify::ParameterAccumulator;
        // A friction term, so that the stuck band (and its widening) excludes samples.
        let setup = setup_with_basis(r#"["sign(u)", "u"]"#);
        let opts = TrackOptions {
            forgetting: 1.0,
            every: 7,
            max_condition: 1e12,
        };
        let mut pushing = Tracker::new(&setup, 0.05, opts);
        let mut following = Tracker::new(&setup, 0.05, opts);
        let mut batch = ParameterAccumulator::new(&setup, 0.05, 1.0);
        for t in [&mut pushing, &mut following] {
            t.widen_band(0, 2e-5, 0.0);
        }
        batch.widen_band(0, 2e-5, 0.0);
        assert!(following.follows_batch());
        for i in 1..=500u64 {
            let d = (i as f64 * 0.37).sin() * 1e-3 + 1e-5 * (i as f64 * 1.3).cos();
            let o = out(
                i,
                d,
                0.5 * d.signum() + 100.0 * d + 0.01 * (i as f64 * 2.1).sin(),
            );
            pushing.push(&o);
            batch.push(&o);
            following.follow(&batch, o.sample);
        }
        let a = pushing.finish(Some(500));
        let b = following.finish_following(Some(&batch), Some(500));
        assert_eq!(a.points.len(), 500 / 7 + 1);
        assert_eq!(a.points, b.points);
        assert!(batch.excluded()[0] > 0, "no sample excluded by the band");
        let forgetting = Tracker::new(
            &setup,
            0.05,
            TrackOptions {
                forgetting: 0.99,
                ..opts
            },
        );
        assert!(!forgetting.follows_batch());
    }

    /// Before enough rows exist the point says why and carries no number.
    #[test]
    fn an_unsolvable_fit_is_recorded_without_a_value() {
        let setup = spring_setup();
        let mut t = Tracker::new(
            &setup,
            1e-6,
            TrackOptions {
                forgetting: 1.0,
                every: 1,
                max_condition: 1e12,
            },
        );
        t.push(&out(1, 1e-3, 0.1));
        let track = t.finish(Some(1));
        assert_eq!(track.points.len(), 1);
        assert!(track.points[0].parameters[0].is_none());
        assert!(track.points[0].unsolved[0].contains("too few usable samples"));
    }
}
