//! Order-preserving parallel map over independent simulations of a record.
//!
//! Why: the refinements evaluate a cost at many parameter vectors or model sub-step levels,
//! each a whole simulation of the record (milliseconds to seconds), and the evaluations are
//! independent. Scoped standard-library threads cover that without a new dependency; the
//! results are the same as a sequential run, bit for bit (each item is computed by the same
//! code on its own data), only sooner.
//!
//! The number of threads is `JOINTID_THREADS` if set (≥ 1), else the machine's available
//! parallelism ([`join_beside`] adds one thread for a short side job). `jointid live` identifies its windows on a worker thread while the stream
//! runs, so these threads share the cores with its stepper (BENCHMARKS.md: residual latency
//! p99 15–20 ms instead of 2 ms on 2 cores); `JOINTID_THREADS=1` keeps an identification on
//! one core.

use std::cell::Cell;
use std::sync::atomic::{AtomicUsize, Ordering};

thread_local! {
    /// Whether this thread is running an item of a parallel [`map_with`].
    static IN_PARALLEL_MAP: Cell<bool> = const { Cell::new(false) };
    /// The threads a [`map`] called on this thread may use: 0 outside any parallel map
    /// ([`threads`]); inside one, its share of the enclosing map's threads (see
    /// [`InParallelMap`]).
    static THREAD_SHARE: Cell<usize> = const { Cell::new(0) };
}

/// Threads for a parallel map: `JOINTID_THREADS` (≥ 1) or the available parallelism.
pub fn threads() -> usize {
    std::env::var("JOINTID_THREADS")
        .ok()
        .and_then(|s| s.trim().parse::<usize>().ok())
        .filter(|n| *n >= 1)
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

/// `items.iter().map(f).collect()`, with the items shared among scoped threads (each takes
/// the next unclaimed item). The order of the results is that of the items.
///
/// Threads: [`threads`] at the top level; inside an item of a parallel map, that item's
/// share of the enclosing map's threads (at least 1: one item after the other). Why: the
/// bootstrap's replicates are a parallel map of whole identifications, each of which maps
/// its own runs; with every level taking all the cores, `N` cores ran up to `N²` threads
/// (a review finding of the thirty-ninth session). The results do not depend on the threads.
pub fn map<T: Sync, R: Send>(items: &[T], f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    map_with(available(), items, f)
}

/// The threads a map called here may use (see [`map`]).
fn available() -> usize {
    match THREAD_SHARE.with(Cell::get) {
        0 => threads(),
        share => share,
    }
}

/// Sets [`IN_PARALLEL_MAP`] and [`THREAD_SHARE`] for its life and puts the former values
/// back when dropped, also when an item panics (`jointid live` catches a window's panic and
/// keeps its worker thread, whose later maps must not take themselves for nested).
struct InParallelMap {
    was: bool,
    share_was: usize,
}

impl InParallelMap {
    /// Entered by each of `workers` threads of a map that had `threads` to share.
    fn enter(threads: usize, workers: usize) -> Self {
        Self {
            was: IN_PARALLEL_MAP.with(|c| c.replace(true)),
            share_was: THREAD_SHARE.with(|c| c.replace((threads / workers.max(1)).max(1))),
        }
    }
}

impl Drop for InParallelMap {
    fn drop(&mut self) {
        IN_PARALLEL_MAP.with(|c| c.set(self.was));
        THREAD_SHARE.with(|c| c.set(self.share_was));
    }
}

/// [`map`], but one item after the other when called from an item of a parallel map, even
/// where that item's share of the threads ([`map`]) is more than one: for the inner level
/// of work that is also run on its own and whose outer level has as many items as cores or
/// more (the maximum-likelihood Jacobian: inside the parallel descents of its start grid,
/// alone in its homotopy's stages), where a share of one is the usual case and the
/// sequential order is what was measured.
pub fn map_unless_nested<T: Sync, R: Send>(items: &[T], f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    if IN_PARALLEL_MAP.with(Cell::get) {
        items.iter().map(f).collect()
    } else {
        map(items, f)
    }
}

/// [`map`] on at most `threads` threads.
pub fn map_with<T: Sync, R: Send>(
    threads: usize,
    items: &[T],
    f: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    let workers = threads.min(items.len());
    if workers <= 1 {
        return items.iter().map(f).collect();
    }
    let next = AtomicUsize::new(0);
    let work = || {
        let _inside = InParallelMap::enter(threads, workers);
        let mut done = Vec::new();
        loop {
            let i = next.fetch_add(1, Ordering::Relaxed);
            let Some(item) = items.get(i) else { break };
            done.push((i, f(item)));
        }
        done
    };
    // The calling thread is one of the workers (it would only wait otherwise): one thread
    // fewer to start per map, and a map is a few milliseconds.
    let mut parts: Vec<Vec<(usize, R)>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (1..workers).map(|_| scope.spawn(work)).collect();
        let mut parts = vec![work()];
        parts.extend(
            handles
                .into_iter()
                .map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))),
        );
        parts
    });
    let mut all: Vec<(usize, R)> = parts.drain(..).flatten().collect();
    all.sort_by_key(|(i, _)| *i);
    all.into_iter().map(|(_, r)| r).collect()
}

/// `(main(), beside())`: `main` on the calling thread with its threads as they are, and
/// `beside`, a short side job, on one more thread of its own whose maps run one item after
/// the other (a share of one). Why: the side job fills the gaps a parallel `main` leaves
/// (its sequential steps: a descent's trials) instead of taking half the cores from it for
/// its whole length, as a two-item [`map`] would. The results are those of the sequential
/// calls. Without a second thread (`JOINTID_THREADS=1`, or inside an item with a share of
/// one) the two run one after the other on the calling thread.
pub fn join_beside<A: Send, B: Send>(
    main: impl FnOnce() -> A + Send,
    beside: impl FnOnce() -> B + Send,
) -> (A, B) {
    if available() <= 1 {
        return (main(), beside());
    }
    std::thread::scope(|scope| {
        let side = scope.spawn(|| {
            let _inside = InParallelMap::enter(1, 1);
            beside()
        });
        let a = main();
        let b = side.join().unwrap_or_else(|e| std::panic::resume_unwind(e));
        (a, b)
    })
}

/// Wall time of the identification's phases, printed to stderr when `JOINTID_TIMING` is set
/// (how BENCHMARKS.md splits an identification; no cost when unset). `phase("name", t0)`
/// prints the time since `t0`.
pub fn phase(name: &str, since: std::time::Instant) {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    if *ON.get_or_init(|| std::env::var_os("JOINTID_TIMING").is_some()) {
        eprintln!(
            "timing: {name:<28} {:>9.1} ms",
            since.elapsed().as_secs_f64() * 1e3
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Inside a parallel map's item, `map_unless_nested` runs one item after the other (the
    /// same results); outside it, and after a map whose item panicked, it is parallel again
    /// (the flag is put back by a drop guard, as `jointid live`, which catches a window's
    /// panic and keeps its thread, needs).
    #[test]
    fn the_nested_flag_is_set_inside_a_parallel_map_and_restored_after_a_panic() {
        let nested = || IN_PARALLEL_MAP.with(Cell::get);
        assert!(!nested());
        let seen = map_with(2, &[0u32, 1, 2, 3], |x| {
            let inner = map_unless_nested(&[1u32, 2], |y| x * 10 + y);
            (nested(), inner)
        });
        assert!(seen.iter().all(|(inside, _)| *inside));
        assert_eq!(seen[3].1, vec![31, 32]);
        assert!(!nested());
        let caught = std::panic::catch_unwind(|| {
            // Every item panics, so the calling thread's own share does too.
            map_with(2, &[0u32, 1], |_| -> u32 { panic!("planted panic") })
        });
        assert!(caught.is_err());
        assert!(
            !nested(),
            "the calling thread must not stay marked as inside a map"
        );
        assert_eq!(
            THREAD_SHARE.with(Cell::get),
            0,
            "nor keep a thread share after the panic"
        );
    }

    /// `join_beside` gives the same results as the two calls in turn; its side job's maps
    /// run on one thread (its own), and the calling thread's share is untouched.
    #[test]
    fn a_side_job_runs_its_maps_on_its_own_thread_and_returns_both_results() {
        let ((main_sum, main_share), (side_threads, side_sum)) = join_beside(
            || {
                (
                    map(&[1u64, 2, 3], |x| x * x).iter().sum::<u64>(),
                    available(),
                )
            },
            || {
                let ids = map(&[0u8; 6], |_| std::thread::current().id());
                let mut distinct = ids.clone();
                distinct.sort_by_key(|id| format!("{id:?}"));
                distinct.dedup();
                (
                    distinct.len(),
                    map(&[4u64, 5], |x| x + 1).iter().sum::<u64>(),
                )
            },
        );
        assert_eq!((main_sum, side_sum), (14, 11));
        assert_eq!(side_threads, 1);
        // With a second thread the side job runs on its own; a panic in it reaches the
        // caller.
        let caller = std::thread::current().id();
        let (_, side) = join_beside(|| (), || std::thread::current().id());
        assert_eq!(side != caller, available() > 1);
        let caught = std::panic::catch_unwind(|| join_beside(|| 1, || -> u8 { panic!("planted") }));
        assert!(caught.is_err());
        assert_eq!(main_share, available());
        assert_eq!(THREAD_SHARE.with(Cell::get), 0);
    }

    /// A map inside an item of a parallel map gets that item's share of the threads: two
    /// items of a four-thread map run their inner maps on two threads each, four items on
    /// one (one item after the other, on the item's own thread); the share is put back after
    /// the map. The results are those of the sequential map.
    #[test]
    fn a_nested_map_shares_the_enclosing_maps_threads() {
        let threads_seen = |outer_items: usize| {
            let items: Vec<usize> = (0..outer_items).collect();
            map_with(4, &items, |_| {
                let inner: Vec<std::thread::ThreadId> =
                    map(&[0u8; 8], |_| std::thread::current().id());
                let mut distinct = inner.clone();
                distinct.sort_by_key(|id| format!("{id:?}"));
                distinct.dedup();
                (available(), distinct.len())
            })
        };
        for (available_inside, distinct) in threads_seen(2) {
            assert_eq!(available_inside, 2);
            assert!(distinct <= 2, "{distinct} threads for a share of 2");
        }
        for (available_inside, distinct) in threads_seen(4) {
            assert_eq!(available_inside, 1);
            assert_eq!(distinct, 1);
        }
        assert_eq!(THREAD_SHARE.with(Cell::get), 0);
        let nested: Vec<Vec<u32>> = map_with(3, &[1u32, 2, 3], |x| map(&[10u32, 20], |y| x * y));
        assert_eq!(nested, vec![vec![10, 20], vec![20, 40], vec![30, 60]]);
    }

    /// The parallel map returns what the sequential map returns, in the items' order.
    #[test]
    fn parallel_map_equals_sequential_map() {
        let items: Vec<u64> = (0..257).collect();
        let f = |x: &u64| (0..*x).fold(*x, |a, k| a.wrapping_mul(31).wrapping_add(k));
        let seq: Vec<u64> = items.iter().map(f).collect();
        assert_eq!(map(&items, f), seq);
        // Several threads whatever the machine or JOINTID_THREADS say.
        assert_eq!(map_with(4, &items, f), seq);
        assert!(map_with(4, &Vec::<u64>::new(), f).is_empty());
    }
}
