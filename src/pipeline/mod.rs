//! The streaming pipeline (DESIGN.md §3): **source → aligner → stepper → refitter →
//! sinks**, one thread per stage, joined by bounded crossbeam channels.
//!
//! The same stages serve the three sources: an MCAP recording ([`replay`]), live iceoryx2
//! subscriptions and the synthetic `acquire-sim` publisher ([`live`]).
//!
//! # Messages and shutdown
//!
//! Every channel carries [`Msg`]: `Data(item)`, then exactly one end message that says how
//! the stream ended:
//!
//! * [`Msg::Flush`]: the stream ended cleanly (end of file, end-of-stream frames on both
//!   live streams, a `--samples`/`--seconds` limit). A stage finishes what it holds (a
//!   smoother's tail, the final refit), sends its last data and passes `Flush` on.
//! * [`Msg::Quit`]: stop now. `error: None` is a requested stop (Ctrl-C); `Some` names the
//!   failure (a source read error, a fatal fault). A stage still drains what it holds and
//!   finalises its outputs, so a recording written so far is complete and renamed from
//!   `.partial`, then passes the `Quit` on with the same error.
//!
//! A stage whose downstream has gone away (a receiver dropped because that stage failed)
//! stops forwarding but keeps draining its input, so no upstream stage ever blocks on a
//! full channel forever. The orchestrator joins every thread; a panicking stage is
//! reported as an error, never ignored.
//!
//! # Channel sizes
//!
//! [`CHANNEL_CAPACITY`] messages per channel (4096: 80 ms at 51.2 kHz). Between stages the
//! policy is backpressure (a full channel blocks the sender), because every sample
//! matters to the identification; the only lossy edges are the outgoing iceoryx2
//! publications to viewers (see [`live`]).

pub mod acquire;
pub mod live;
pub mod replay;

use std::collections::VecDeque;

use crossbeam_channel::{Receiver, Sender};

use crate::align::{AlignError, Aligner};
use crate::io::Frame;
use crate::io::mcap::InputTopic;

/// Messages per inter-stage channel (80 ms of samples at 51.2 kHz).
pub const CHANNEL_CAPACITY: usize = 4096;

/// One message on a pipeline channel; see the module docs.
#[derive(Debug, Clone, PartialEq)]
pub enum Msg<T> {
    Data(T),
    /// Clean end of the stream: finish, finalise, pass on.
    Flush,
    /// Stop: `None` = requested (Ctrl-C), `Some` = the failure that ended the stream.
    Quit {
        error: Option<String>,
    },
}

impl<T> Msg<T> {
    /// The end message with the item type changed (for forwarding an end downstream).
    pub fn end_as<U>(&self) -> Option<Msg<U>> {
        match self {
            Msg::Data(_) => None,
            Msg::Flush => Some(Msg::Flush),
            Msg::Quit { error } => Some(Msg::Quit {
                error: error.clone(),
            }),
        }
    }
}

/// What a source emits.
#[derive(Debug, Clone, PartialEq)]
pub enum SourceItem {
    /// One frame of one input stream.
    Frame(InputTopic, Frame),
    /// A problem with the input that does not stop the stream (a truncated file, a
    /// publisher that vanished without end-of-stream); reported with the results.
    Warning(String),
    /// Something worth telling that is not a problem.
    Notice(String),
    /// A publisher of this stream (re)appeared: its next frame may start a new run.
    Appeared(InputTopic),
}

/// One aligned sample: excitation and response of the same sample index, in setup
/// channel order, SI units.
#[derive(Debug, Clone, PartialEq)]
pub struct Aligned {
    pub sample: u64,
    pub t_ns: u64,
    pub excitation: Vec<f64>,
    pub response: Vec<f64>,
}

/// What an aligner emits.
#[derive(Debug, Clone, PartialEq)]
pub enum AlignedItem {
    Sample(Aligned),
    /// Forwarded from the source.
    Warning(String),
    /// The input violated the aligner's checks; under the strict (replay) policy no
    /// further sample follows.
    Fault(AlignError),
}

/// Sends unless the receiver is gone; returns whether the receiver is still there.
pub(crate) fn forward<T>(tx: &Sender<Msg<T>>, msg: Msg<T>) -> bool {
    tx.send(msg).is_ok()
}

/// The replay aligner stage (strict policy, the one `align::align` applies to whole
/// lists): frames are paired in arrival order per topic, `Aligner::push` checks each
/// pair, and the first violation is forwarded as [`AlignedItem::Fault`] after which no
/// sample is forwarded (the input is still drained so the source finishes and reports
/// its own errors). At the end, frames left over on one topic are an
/// [`AlignError::Unpaired`] fault naming the first of them.
pub fn strict_align_stage(
    rx: Receiver<Msg<SourceItem>>,
    tx: Sender<Msg<AlignedItem>>,
    mut aligner: Aligner,
) {
    let mut queues: [VecDeque<Frame>; 2] = [VecDeque::new(), VecDeque::new()];
    let mut failed = false;
    let mut downstream = true;
    let send = |tx: &Sender<Msg<AlignedItem>>, item: AlignedItem, downstream: &mut bool| {
        if *downstream {
            *downstream = forward(tx, Msg::Data(item));
        }
    };
    let end = loop {
        let Ok(msg) = rx.recv() else {
            break Msg::Quit {
                error: Some("the source stage ended without an end message".into()),
            };
        };
        match msg {
            Msg::Data(SourceItem::Warning(w)) => {
                send(&tx, AlignedItem::Warning(w), &mut downstream)
            }
            Msg::Data(SourceItem::Frame(topic, frame)) => {
                if failed {
                    continue;
                }
                queues[topic_index(topic)].push_back(frame);
                while !queues[0].is_empty() && !queues[1].is_empty() {
                    let (Some(e), Some(r)) = (queues[0].pop_front(), queues[1].pop_front()) else {
                        break;
                    };
                    match aligner.push(&e, &r) {
                        Ok(()) => send(
                            &tx,
                            AlignedItem::Sample(Aligned {
                                sample: e.sample,
                                t_ns: e.t_ns,
                                excitation: e.values,
                                response: r.values,
                            }),
                            &mut downstream,
                        ),
                        Err(err) => {
                            failed = true;
                            queues = [VecDeque::new(), VecDeque::new()];
                            send(&tx, AlignedItem::Fault(err), &mut downstream);
                        }
                    }
                }
            }
            end => break end,
        }
    };
    if !failed {
        let left = if let Some(f) = queues[0].front() {
            Some((f.sample, "excitation", "response"))
        } else {
            queues[1]
                .front()
                .map(|f| (f.sample, "response", "excitation"))
        };
        if let Some((sample, present, missing)) = left {
            send(
                &tx,
                AlignedItem::Fault(AlignError::Unpaired {
                    sample,
                    present,
                    missing,
                }),
                &mut downstream,
            );
        }
    }
    if downstream && let Some(end) = end.end_as() {
        let _ = tx.send(end);
    }
}

/// Queue index of a topic (excitation 0, response 1).
pub(crate) fn topic_index(topic: InputTopic) -> usize {
    match topic {
        InputTopic::Excitation => 0,
        InputTopic::Response => 1,
    }
}

/// Turns a stage thread's panic payload into an error message naming the stage.
pub(crate) fn panic_message(name: &str, p: Box<dyn std::any::Any + Send>) -> String {
    let what = p
        .downcast_ref::<String>()
        .cloned()
        .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_else(|| "unknown panic".into());
    format!("pipeline stage `{name}` panicked: {what}")
}
