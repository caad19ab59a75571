//! The aligner: joins excitation and response frames by sample index and checks what the
//! estimators assume — consecutive samples at the setup's interval, finite values, the
//! setup's channel counts. Policy (stated): any violation is an error naming the topic and
//! the sample; the frames before it are kept so a replay can still use them.

use crate::identify::TestData;
use crate::io::Frame;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AlignError {
    #[error("{topic} sample {sample}: {got} values, the setup has {expected} channels")]
    WrongChannelCount {
        topic: &'static str,
        sample: u64,
        expected: usize,
        got: usize,
    },
    #[error("{topic} sample {sample}: channel {channel} is not finite ({value})")]
    NonFinite {
        topic: &'static str,
        sample: u64,
        channel: usize,
        value: f64,
    },
    #[error("sample {sample} is on {present} but missing from {missing}")]
    Unpaired {
        sample: u64,
        present: &'static str,
        missing: &'static str,
    },
    #[error("gap in the samples: {prev} is followed by {got} (a gap breaks the time stepping)")]
    Gap { prev: u64, got: u64 },
    #[error("{topic} sample {sample}: duplicated or out of order after sample {prev}")]
    OutOfOrder {
        topic: &'static str,
        sample: u64,
        prev: u64,
    },
    #[error(
        "sample {sample}: time step {got_s:.6e} s differs from the setup's dt_s = {dt_s:.6e} s by more than 1 %"
    )]
    WrongInterval { sample: u64, got_s: f64, dt_s: f64 },
    #[error("sample {sample}: time goes backwards ({prev_ns} ns, then {got_ns} ns)")]
    NonMonotonicTime {
        sample: u64,
        prev_ns: u64,
        got_ns: u64,
    },
}

/// Incremental aligner (the pipeline's stage and the batch path share it).
#[derive(Debug, Clone)]
pub struct Aligner {
    n_excitation: usize,
    n_response: usize,
    dt_ns: f64,
    last: Option<(u64, u64)>,
    gaps_allowed: bool,
}

impl Aligner {
    pub fn new(n_excitation: usize, n_response: usize, dt_s: f64) -> Self {
        Self {
            n_excitation,
            n_response,
            dt_ns: dt_s * 1e9,
            last: None,
            gaps_allowed: false,
        }
    }

    /// An aligner that accepts a gap in the sample indices (frames lost, a restarted
    /// acquisition recorded after a one-sample gap): a windowed identification
    /// (`crate::session`) restarts its window after it. The time checks (interval and
    /// monotonic time) are skipped across the gap (a restarted acquisition's clock may
    /// start anywhere); the others stay.
    pub fn allowing_gaps(mut self) -> Self {
        self.gaps_allowed = true;
        self
    }

    fn check_frame(
        &self,
        topic: &'static str,
        f: &Frame,
        expected: usize,
    ) -> Result<(), AlignError> {
        if f.values.len() != expected {
            return Err(AlignError::WrongChannelCount {
                topic,
                sample: f.sample,
                expected,
                got: f.values.len(),
            });
        }
        if let Some((channel, &value)) = f.values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(AlignError::NonFinite {
                topic,
                sample: f.sample,
                channel,
                value,
            });
        }
        Ok(())
    }

    /// Accept one pair of frames for the same sample.
    pub fn push(&mut self, excitation: &Frame, response: &Frame) -> Result<(), AlignError> {
        self.check_frame("excitation", excitation, self.n_excitation)?;
        self.check_frame("response", response, self.n_response)?;
        if excitation.sample != response.sample {
            let (sample, present, missing) = if excitation.sample < response.sample {
                (excitation.sample, "excitation", "response")
            } else {
                (response.sample, "response", "excitation")
            };
            return Err(AlignError::Unpaired {
                sample,
                present,
                missing,
            });
        }
        let (s, t) = (excitation.sample, excitation.t_ns);
        if let Some((ps, pt)) = self.last {
            if s <= ps {
                return Err(AlignError::OutOfOrder {
                    topic: "excitation",
                    sample: s,
                    prev: ps,
                });
            }
            if s != ps + 1 {
                if !self.gaps_allowed {
                    return Err(AlignError::Gap { prev: ps, got: s });
                }
                self.last = Some((s, t));
                return Ok(());
            }
            if t < pt {
                return Err(AlignError::NonMonotonicTime {
                    sample: s,
                    prev_ns: pt,
                    got_ns: t,
                });
            }
            let dt = (t - pt) as f64;
            if (dt - self.dt_ns).abs() > 0.01 * self.dt_ns {
                return Err(AlignError::WrongInterval {
                    sample: s,
                    got_s: dt * 1e-9,
                    dt_s: self.dt_ns * 1e-9,
                });
            }
        }
        self.last = Some((s, t));
        Ok(())
    }
}

/// Align whole frame lists into test data. On error, returns the data aligned before the
/// offending sample together with the error.
pub fn align(
    excitation: &[Frame],
    response: &[Frame],
    n_excitation: usize,
    n_response: usize,
    dt_s: f64,
) -> (TestData, Option<AlignError>) {
    let mut al = Aligner::new(n_excitation, n_response, dt_s);
    let mut data = TestData::default();
    let n = excitation.len().min(response.len());
    for i in 0..n {
        if let Err(e) = al.push(&excitation[i], &response[i]) {
            return (data, Some(e));
        }
        data.samples.push(excitation[i].sample);
        data.t_ns.push(excitation[i].t_ns);
        data.excitation.push(excitation[i].values.clone());
        data.response.push(response[i].values.clone());
    }
    if excitation.len() != response.len() {
        let (sample, present, missing) = if excitation.len() > response.len() {
            (excitation[n].sample, "excitation", "response")
        } else {
            (response[n].sample, "response", "excitation")
        };
        return (
            data,
            Some(AlignError::Unpaired {
                sample,
                present,
                missing,
            }),
        );
    }
    (data, None)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fr(sample: u64, t_ns: u64, values: Vec<f64>) -> Frame {
        Frame {
            sample,
            t_ns,
            values,
        }
    }

    #[test]
    fn keeps_what_came_before_a_bad_sample() {
        let e: Vec<Frame> = (0..5).map(|i| fr(i, i * 1000, vec![1.0])).collect();
        let mut r: Vec<Frame> = (0..5).map(|i| fr(i, i * 1000, vec![1.0, 2.0])).collect();
        r[3].values[1] = f64::NAN;
        let (d, err) = align(&e, &r, 1, 2, 1e-6);
        assert_eq!(d.len(), 3);
        assert!(matches!(
            err,
            Some(AlignError::NonFinite {
                topic: "response",
                sample: 3,
                channel: 1,
                ..
            })
        ));
        assert!(
            err.unwrap()
                .to_string()
                .contains("response sample 3: channel 1")
        );
    }

    #[test]
    fn gaps_wrong_interval_and_channel_count_are_named() {
        let e = vec![fr(0, 0, vec![1.0]), fr(2, 2000, vec![1.0])];
        let r = vec![fr(0, 0, vec![1.0]), fr(2, 2000, vec![1.0])];
        assert_eq!(
            align(&e, &r, 1, 1, 1e-6).1,
            Some(AlignError::Gap { prev: 0, got: 2 })
        );
        let e = vec![fr(0, 0, vec![1.0]), fr(1, 1500, vec![1.0])];
        let r = e.clone();
        assert!(matches!(
            align(&e, &r, 1, 1, 1e-6).1,
            Some(AlignError::WrongInterval { sample: 1, .. })
        ));
        let r = vec![fr(0, 0, vec![1.0, 2.0])];
        assert!(matches!(
            align(&e[..1], &r, 1, 1, 1e-6).1,
            Some(AlignError::WrongChannelCount {
                topic: "response",
                sample: 0,
                expected: 1,
                got: 2
            })
        ));
    }
}
