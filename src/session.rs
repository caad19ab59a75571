//! Whole-session identification with bounded memory: **windows** of `W` contiguous samples
//! started every `S` samples, each identified on its own ([`crate::identify::identify`],
//! exactly what `jointid replay` does with a `W`-sample record), combined per parameter by
//! inverse-variance weighting.
//!
//! # Why windows
//!
//! The default identification needs its whole record at once (noise levels from the
//! record, likelihood-tuned filter, smoother, prediction-error refinement), and costs about
//! 1 ms per sample on the paper model. A 60 s session at 51.2 kHz is 3 million samples:
//! neither the memory nor the time of one batch over it is available while the test runs.
//! Disjoint windows are independent experiments (the measurement noise is white), so their
//! estimates combine like repeated measurements; memory is one window however long the
//! record, and the windows are a deterministic function of the sample indices, so anyone
//! replaying the record with the same `W` and `S` (`[estimator] window_samples`,
//! `window_every` in the setup) gets the same numbers. `jointid replay` uses it when the
//! setup asks; `jointid live` always does (its windows are identified on a worker thread
//! while the test runs, and the recording's attached setup carries the window keys, so
//! `jointid replay` on the recording repeats them).
//!
//! # Schedule (deterministic from the sample indices)
//!
//! The first window starts at the first sample. A window collects `W` contiguous samples;
//! a gap (lost frames, a restarted acquisition) abandons it, and it starts again at the
//! first sample after the gap. When a window is complete, the next one starts at the first
//! sample at or after its start + `S`. Records that start in motion are the rule here
//! (every window but the first starts mid-test): maximum likelihood and the Kalman
//! pipeline for `sign(u)` laws estimate the initial state; the others refuse such a window,
//! which is then left out and counted (ACCURACY.md, "Records that start in motion").
//!
//! # Combination
//!
//! Per parameter, `x̄ = Σ wᵢ xᵢ / Σ wᵢ` with `wᵢ = 1/seᵢ²`, standard error `1/√Σwᵢ`,
//! widened by the Birge ratio `√(χ²/(k − 1))` when it exceeds 1
//! (`χ² = Σ wᵢ (xᵢ − x̄)²`): windows that disagree beyond their stated errors (a joint that
//! changes during the test, or errors stated too small) widen the combined error instead of
//! letting it shrink as `1/√k`. A window whose identification fails, or gives a non-finite
//! or non-positive error for a parameter, is left out of that combination and counted.

use serde::Serialize;

use crate::identify::{Identification, IdentifyError, IdentifyOptions, TestData, identify};
use crate::setup::Setup;

/// Fewest samples per window (the identification's stiffness scan alone reads 200).
pub const MIN_WINDOW_SAMPLES: usize = 400;

/// Window length and stride, in samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct WindowSpec {
    /// Samples per window (`W`).
    pub samples: usize,
    /// Samples from one window's start to the next one's (`S ≥ W`).
    pub every: usize,
}

impl WindowSpec {
    /// `every` is raised to `samples` (windows do not overlap: overlapping windows are not
    /// independent, and the combination would overstate the precision).
    pub fn new(samples: usize, every: usize) -> Self {
        Self {
            samples,
            every: every.max(samples),
        }
    }
}

/// Collects the scheduled windows from a stream of samples (see the module docs).
#[derive(Debug, Clone)]
pub struct WindowCollector {
    spec: WindowSpec,
    /// Index at or after which the next window starts (`None` before the first sample).
    next_start: Option<u64>,
    /// The record's first sample: a window that starts there may be at rest, every other
    /// one starts in motion.
    record_first: Option<u64>,
    current: TestData,
    /// Windows completed so far.
    pub completed: usize,
    /// Windows abandoned at a gap.
    pub abandoned: usize,
}

impl WindowCollector {
    pub fn new(spec: WindowSpec) -> Self {
        Self {
            spec,
            next_start: None,
            record_first: None,
            current: TestData::default(),
            completed: 0,
            abandoned: 0,
        }
    }

    pub fn spec(&self) -> WindowSpec {
        self.spec
    }

    /// Whether [`WindowCollector::push`] would keep this sample's values (a caller that
    /// must copy them can skip the copy otherwise and push empty ones).
    pub fn keeps(&self, sample: u64) -> bool {
        match self.current.samples.last() {
            Some(&last) if sample == last.wrapping_add(1) => true,
            _ => sample >= self.next_start.unwrap_or(sample),
        }
    }

    /// The record's first sample (`None` before it).
    pub fn record_first(&self) -> Option<u64> {
        self.record_first
    }

    /// Takes one aligned sample; returns a window when this sample completes it.
    pub fn push(
        &mut self,
        sample: u64,
        t_ns: u64,
        excitation: Vec<f64>,
        response: Vec<f64>,
    ) -> Option<TestData> {
        self.record_first.get_or_insert(sample);
        let start = *self.next_start.get_or_insert(sample);
        if let Some(&last) = self.current.samples.last()
            && sample != last.wrapping_add(1)
        {
            // A gap: the time stepping cannot cross it; start again after it.
            self.current = TestData::default();
            self.abandoned += 1;
        }
        if self.current.is_empty() && sample < start {
            return None;
        }
        self.current.samples.push(sample);
        self.current.t_ns.push(t_ns);
        self.current.excitation.push(excitation);
        self.current.response.push(response);
        if self.current.len() < self.spec.samples {
            return None;
        }
        let first = self.current.samples[0];
        self.next_start = Some(first.saturating_add(self.spec.every as u64));
        self.completed += 1;
        Some(std::mem::take(&mut self.current))
    }

    /// The samples of the window being collected (at the end of a session shorter than one
    /// window, the whole session is identified as one window).
    pub fn take_partial(&mut self) -> TestData {
        std::mem::take(&mut self.current)
    }

    /// Samples held (the memory the collector needs: at most one window).
    pub fn held(&self) -> usize {
        self.current.len()
    }
}

/// One window's identification, as combined.
#[derive(Debug, Clone, Serialize)]
pub struct WindowEstimate {
    pub first_sample: u64,
    pub last_sample: u64,
    /// `(value, standard error)` per parameter in setup key order; empty when the
    /// identification failed.
    pub parameters: Vec<(f64, f64)>,
    /// Why the window gave no parameters, if it did not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub failure: Option<String>,
}

/// The combined estimate of every parameter over the windows.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Combined {
    pub values: Vec<f64>,
    pub std_errors: Vec<f64>,
    /// Windows that entered each parameter's combination.
    pub windows: Vec<usize>,
    /// Birge ratio `√(χ²/(k − 1))` per parameter (1 with one window); the standard error
    /// is widened by it when it exceeds 1.
    pub birge_ratio: Vec<f64>,
}

/// Combine window estimates (module docs); `None` when no window has parameters.
pub fn combine(estimates: &[WindowEstimate]) -> Option<Combined> {
    let p = estimates.iter().map(|e| e.parameters.len()).max()?;
    if p == 0 {
        return None;
    }
    let mut out = Combined {
        values: vec![f64::NAN; p],
        std_errors: vec![f64::NAN; p],
        windows: vec![0; p],
        birge_ratio: vec![f64::NAN; p],
    };
    for j in 0..p {
        let usable: Vec<(f64, f64)> = estimates
            .iter()
            .filter_map(|e| e.parameters.get(j).copied())
            .filter(|(v, se)| v.is_finite() && se.is_finite() && *se > 0.0)
            .map(|(v, se)| (v, 1.0 / (se * se)))
            .collect();
        let k = usable.len();
        if k == 0 {
            continue;
        }
        let wsum: f64 = usable.iter().map(|(_, w)| w).sum();
        let mean = usable.iter().map(|(v, w)| v * w).sum::<f64>() / wsum;
        let chi2: f64 = usable.iter().map(|(v, w)| w * (v - mean).powi(2)).sum();
        let birge = if k > 1 {
            (chi2 / (k - 1) as f64).sqrt()
        } else {
            1.0
        };
        out.values[j] = mean;
        out.std_errors[j] = wsum.sqrt().recip() * birge.max(1.0);
        out.windows[j] = k;
        out.birge_ratio[j] = birge;
    }
    Some(out)
}

/// What a windowed identification reports beside the last window's passes.
#[derive(Debug, Clone, Serialize)]
pub struct SessionReport {
    pub window_samples: usize,
    pub window_every: usize,
    /// Samples seen in the whole record or session.
    pub samples_seen: usize,
    /// Windows abandoned at a gap.
    pub windows_abandoned: usize,
    /// Every identified window, in order.
    pub windows: Vec<WindowEstimate>,
    /// Their combination (what the parameters carry).
    pub combined: Option<Combined>,
}

impl SessionReport {
    pub fn new(spec: WindowSpec) -> Self {
        Self {
            window_samples: spec.samples,
            window_every: spec.every,
            samples_seen: 0,
            windows_abandoned: 0,
            windows: Vec::new(),
            combined: None,
        }
    }
}

/// Identify one window: `identify` over its samples, told that the window starts
/// mid-record (in motion) unless it starts at the record's first sample `record_first`
/// ([`IdentifyOptions::starts_mid_record`]: with accelerometers only a start in motion
/// cannot be seen in the data). Returns the estimate to combine and the identification.
pub fn identify_window(
    setup: &Setup,
    data: &TestData,
    opts: &IdentifyOptions,
    truth: Option<&[f64]>,
    record_first: Option<u64>,
    earlier: &[WindowEstimate],
    on_pass: &mut dyn FnMut(&crate::identify::PassReport),
) -> (WindowEstimate, Result<Identification, IdentifyError>) {
    let first = data.samples.first().copied();
    let id = if first.is_some() && first != record_first {
        let opts = IdentifyOptions {
            starts_mid_record: first,
            prior: prior_of(earlier).or_else(|| opts.prior.clone()),
            ..opts.clone()
        };
        identify(setup, data, &opts, truth, on_pass, &mut |_, _| {})
    } else {
        identify(setup, data, opts, truth, on_pass, &mut |_, _| {})
    };
    let mut est = WindowEstimate {
        first_sample: data.samples.first().copied().unwrap_or(0),
        last_sample: data.samples.last().copied().unwrap_or(0),
        parameters: Vec::new(),
        failure: None,
    };
    match &id {
        Ok(i) => match (&i.failure, i.final_parameters()) {
            (None, Some(ps)) => {
                est.parameters = ps.iter().map(|p| (p.value, p.std_error)).collect();
            }
            (Some(f), _) => est.failure = Some(f.clone()),
            (None, None) => est.failure = Some("the identification has no parameters".into()),
        },
        Err(e) => est.failure = Some(e.to_string()),
    }
    (est, id)
}

/// Where a window that starts mid-record begins its refinement: the combination of the
/// windows identified before it, when every parameter has one (`IdentifyOptions::prior`
/// says why). Both `jointid replay` and `jointid live` identify the windows in order on one
/// thread, so both start each window from the same values and give the same answer.
fn prior_of(earlier: &[WindowEstimate]) -> Option<crate::identify::Prior> {
    let c = combine(earlier)?;
    let good = earlier.iter().filter(|w| w.failure.is_none()).count();
    let complete = c
        .values
        .iter()
        .zip(&c.std_errors)
        .all(|(v, e)| v.is_finite() && e.is_finite() && *e > 0.0);
    complete.then(|| crate::identify::Prior {
        values: c.values,
        std_errors: c.std_errors,
        source: format!(
            "the combination of the {good} earlier window{} of the session",
            if good == 1 { "" } else { "s" }
        ),
    })
}

/// The running state of a windowed identification, shared by `jointid replay` and
/// `jointid live` so that both show the same thing: every window's estimate, every good
/// window's Cramér–Rao bounds, and the identification shown (the last good window's; a
/// failed one only while no window was good), with the data it came from.
#[derive(Debug)]
pub struct WindowedSession<E> {
    pub report: SessionReport,
    bounds: Vec<Vec<Option<f64>>>,
    last: Option<(TestData, Result<Identification, E>)>,
}

impl<E> WindowedSession<E> {
    pub fn new(spec: WindowSpec) -> Self {
        Self {
            report: SessionReport::new(spec),
            bounds: Vec::new(),
            last: None,
        }
    }

    /// Adds one identified window (`data`: its samples, kept only for the window shown;
    /// pass an empty one when they are not needed).
    pub fn add(&mut self, est: WindowEstimate, id: Result<Identification, E>, data: TestData) {
        let good = est.failure.is_none();
        if good && let Ok(i) = &id {
            self.bounds.push(
                i.final_parameters()
                    .map(|ps| ps.iter().map(|p| p.crlb).collect())
                    .unwrap_or_default(),
            );
        }
        self.report.windows.push(est);
        // A failed window after good ones does not take their place.
        let shown_is_bad = self
            .last
            .as_ref()
            .is_none_or(|(_, l)| l.as_ref().map_or(true, |i| i.failure.is_some()));
        if good || shown_is_bad {
            self.last = Some((data, id));
        }
    }

    /// Windows identified so far (good or not).
    pub fn windows(&self) -> usize {
        self.report.windows.len()
    }

    /// The combination of the windows so far.
    pub fn combined(&self) -> Option<Combined> {
        combine(&self.report.windows)
    }

    /// The window shown, its final parameters replaced by the combination of all
    /// ([`with_combination`]); `None` when no window was identified.
    pub fn finish(self) -> Option<(TestData, Result<Identification, E>)> {
        let Self {
            report,
            bounds,
            last,
        } = self;
        let (data, id) = last?;
        Some((data, id.map(|i| with_combination(i, report, &bounds))))
    }
}

/// The identification of the last window with its final parameters replaced by the
/// combination of all windows (values, errors, intervals; the Cramér–Rao bound of the
/// combination is `1/√Σ 1/boundᵢ²` when every window has one), the session report
/// attached and a note that says what was combined.
pub fn with_combination(
    mut last: Identification,
    mut report: SessionReport,
    window_bounds: &[Vec<Option<f64>>],
) -> Identification {
    report.combined = combine(&report.windows);
    if let (Some(c), Some(pass)) = (&report.combined, last.passes.last_mut()) {
        for (j, p) in pass.parameters.iter_mut().enumerate() {
            let (Some(&v), Some(&se)) = (c.values.get(j), c.std_errors.get(j)) else {
                continue;
            };
            // No window gave this parameter: the last window's value stays, with its
            // failure noted by the window list.
            if !(v.is_finite() && se.is_finite()) {
                continue;
            }
            p.value = v;
            p.std_error = se;
            p.ci95 = [v - 1.96 * se, v + 1.96 * se];
            let info: Option<f64> = window_bounds
                .iter()
                .map(|b| b.get(j).copied().flatten().map(|x| 1.0 / (x * x)))
                .sum();
            p.crlb = info.filter(|i| *i > 0.0).map(|i| i.sqrt().recip());
        }
        let used = report
            .windows
            .iter()
            .filter(|w| w.failure.is_none())
            .count();
        let worst = c.birge_ratio.iter().copied().fold(0.0, f64::max);
        last.notes.insert(
            0,
            format!(
                "identified in windows of {} samples every {}: {used} of {} windows combined by inverse variance (Birge ratio ≤ {worst:.2}{}); the passes and notes below are the last window's",
                report.window_samples,
                report.window_every,
                report.windows.len(),
                // Widened whenever above 1; said when it shows at two decimals.
                if worst >= 1.005 {
                    ": the windows disagree beyond their errors, which are widened by it"
                } else {
                    ""
                }
            ),
        );
    }
    last.session = Some(report);
    last
}

#[cfg(test)]
mod tests {
    use super::*;

    fn feed(c: &mut WindowCollector, samples: impl IntoIterator<Item = u64>) -> Vec<(u64, u64)> {
        let mut out = Vec::new();
        for s in samples {
            let keeps = c.keeps(s);
            let w = c.push(s, s * 10, vec![s as f64], vec![0.0]);
            let kept = w.is_some() || c.current.samples.last() == Some(&s);
            assert_eq!(keeps, kept, "sample {s}");
            if let Some(w) = w {
                assert_eq!(w.len(), c.spec().samples);
                assert!(w.samples.windows(2).all(|p| p[1] == p[0] + 1));
                assert_eq!(w.excitation[0][0], w.samples[0] as f64);
                out.push((w.samples[0], *w.samples.last().unwrap()));
            }
        }
        out
    }

    /// Windows of W contiguous samples every S samples, from the first sample.
    #[test]
    fn windows_follow_the_schedule() {
        let mut c = WindowCollector::new(WindowSpec::new(4, 10));
        assert_eq!(
            feed(&mut c, 100..135),
            vec![(100, 103), (110, 113), (120, 123), (130, 133)]
        );
        assert_eq!(c.held(), 0);
        // A stride below the window is raised to it: no overlap.
        let mut c = WindowCollector::new(WindowSpec::new(4, 2));
        assert_eq!(feed(&mut c, 0..9), vec![(0, 3), (4, 7)]);
        assert_eq!(c.take_partial().samples, vec![8]);
    }

    /// A gap abandons the window being collected; it starts again after the gap, and the
    /// schedule after it is counted from the window's actual start.
    #[test]
    fn a_gap_restarts_the_window() {
        let mut c = WindowCollector::new(WindowSpec::new(4, 10));
        let samples = (0..2).chain(5..20).chain(40..52);
        assert_eq!(feed(&mut c, samples), vec![(5, 8), (15, 18), (40, 43)]);
        assert_eq!(c.abandoned, 1);
        // A gap inside the idle part of the stride abandons nothing.
        let mut c = WindowCollector::new(WindowSpec::new(3, 10));
        assert_eq!(feed(&mut c, (0..5).chain(7..14)), vec![(0, 2), (10, 12)]);
        assert_eq!(c.abandoned, 0);
    }

    fn est(values: &[(f64, f64)]) -> WindowEstimate {
        WindowEstimate {
            first_sample: 0,
            last_sample: 0,
            parameters: values.to_vec(),
            failure: None,
        }
    }

    /// k consistent windows of equal error: the mean, the error over √k, Birge ratio ≤ 1.
    #[test]
    fn consistent_windows_average_with_shrinking_error() {
        let e = [
            est(&[(1.0, 0.1), (10.0, 2.0)]),
            est(&[(1.1, 0.1), (12.0, 2.0)]),
            est(&[(0.9, 0.1), (11.0, 2.0)]),
            est(&[(1.0, 0.1), (11.0, 2.0)]),
        ];
        let c = combine(&e).unwrap();
        assert!((c.values[0] - 1.0).abs() < 1e-12);
        assert!((c.std_errors[0] - 0.05).abs() < 1e-12);
        assert!(c.birge_ratio[0] <= 1.0);
        assert!((c.values[1] - 11.0).abs() < 1e-12);
        assert!((c.std_errors[1] - 1.0).abs() < 1e-12);
        assert_eq!(c.windows, vec![4, 4]);
    }

    /// The weights are the inverse variances: a window with half the error counts 4×.
    #[test]
    fn weights_are_inverse_variances() {
        let c = combine(&[est(&[(0.0, 1.0)]), est(&[(5.0, 0.5)])]).unwrap();
        assert!((c.values[0] - 4.0).abs() < 1e-12);
        // χ² = 1·16 + 4·1 = 20 → Birge √20: the windows disagree by 4.5 combined errors.
        assert!((c.birge_ratio[0] - 20f64.sqrt()).abs() < 1e-12);
        // 1/√(1 + 4) widened by √20: exactly 2.
        assert!((c.std_errors[0] - 2.0).abs() < 1e-12);
    }

    /// Failed windows and unusable errors are left out; nothing usable gives `None` or NaN.
    #[test]
    fn failed_windows_are_left_out() {
        let mut failed = est(&[]);
        failed.failure = Some("diverged".into());
        assert!(combine(&[failed.clone()]).is_none());
        assert!(combine(&[]).is_none());
        let c = combine(&[
            failed,
            est(&[(2.0, 0.5), (1.0, f64::NAN)]),
            est(&[(3.0, 0.0), (1.0, 0.0)]),
        ])
        .unwrap();
        assert_eq!(c.values[0], 2.0);
        assert_eq!(c.windows, vec![1, 0]);
        assert!(c.values[1].is_nan() && c.std_errors[1].is_nan());
    }
    /// A window starts from the combination of the earlier good windows only when every
    /// parameter has one; with no good window (or one parameter without an estimate) it
    /// starts from its own residual-force estimate.
    #[test]
    fn a_window_starts_from_the_earlier_windows_combination() {
        let mut failed = est(&[]);
        failed.failure = Some("diverged".into());
        assert!(prior_of(&[]).is_none());
        assert!(prior_of(std::slice::from_ref(&failed)).is_none());
        let p = prior_of(&[
            est(&[(1.5, 1.0), (10.0, 2.0)]),
            failed.clone(),
            est(&[(2.5, 1.0), (10.0, 2.0)]),
        ])
        .unwrap();
        assert_eq!(p.values, vec![2.0, 10.0]);
        assert!((p.std_errors[0] - 0.5f64.sqrt()).abs() < 1e-12);
        assert!(p.source.contains("2 earlier windows"), "{}", p.source);
        assert!(prior_of(&[est(&[(1.0, 1.0), (2.0, f64::NAN)])]).is_none());
    }
}
