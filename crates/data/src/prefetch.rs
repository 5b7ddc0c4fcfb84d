//! A multi-threaded prefetching iterator over seeded samples.
//!
//! `W` worker threads produce samples ahead of the consumer: worker `w` produces the indices
//! `start + w, start + w + W, …` into its own bounded queue (`std::sync::mpsc::sync_channel`),
//! and the consumer reads the queues round-robin. The order is therefore always
//! `start, start + 1, …` whatever `W`, at most `W × depth` samples wait in memory, and a
//! worker blocks (instead of racing ahead) when its queue is full. Samples are pure functions
//! of their index, so the items are identical for any number of workers.
//!
//! Dropping the iterator stops the workers (their next send fails) and joins them.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, sync_channel};
use std::thread::JoinHandle;

use crate::DataError;

/// Items in order; see the module documentation.
pub struct Prefetcher<T> {
    receivers: Vec<Receiver<Result<T, DataError>>>,
    handles: Vec<JoinHandle<()>>,
    stop: Arc<AtomicBool>,
    next: u64,
    start: u64,
    end: Option<u64>,
}

impl<T: Send + 'static> Prefetcher<T> {
    /// Produces `make(i)` for `i` in `start..start + count` (endless when `count` is `None`)
    /// with `workers` threads (≥ 1) and `depth` queued items per worker (≥ 1).
    pub fn new<F>(start: u64, count: Option<u64>, workers: usize, depth: usize, make: F) -> Self
    where
        F: Fn(u64) -> Result<T, DataError> + Send + Sync + 'static,
    {
        let workers = workers.max(1);
        let make = Arc::new(make);
        let stop = Arc::new(AtomicBool::new(false));
        let end = count.map(|c| start.saturating_add(c));
        let mut receivers = Vec::with_capacity(workers);
        let mut handles = Vec::with_capacity(workers);
        for w in 0..workers {
            let (tx, rx) = sync_channel(depth.max(1));
            let make = make.clone();
            let stop = stop.clone();
            let handle = std::thread::Builder::new()
                .name(format!("ic-data-prefetch-{w}"))
                .spawn(move || {
                    let mut i = start + w as u64;
                    while end.is_none_or(|e| i < e) && !stop.load(Ordering::Relaxed) {
                        let item =
                            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| make(i)))
                                .unwrap_or_else(|_| {
                                    Err(DataError::Worker(format!("sample {i} panicked")))
                                });
                        if tx.send(item).is_err() {
                            break;
                        }
                        i += workers as u64;
                    }
                })
                .expect("spawning a prefetch thread");
            receivers.push(rx);
            handles.push(handle);
        }
        Prefetcher {
            receivers,
            handles,
            stop,
            next: start,
            start,
            end,
        }
    }

    /// Groups the items into batches of `size` (≥ 1); the last batch may be shorter. A batch
    /// with a failed item yields that item's error.
    pub fn batches(self, size: usize) -> Batches<T> {
        Batches {
            inner: self,
            size: size.max(1),
        }
    }
}

impl<T> Iterator for Prefetcher<T> {
    type Item = Result<T, DataError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.end.is_some_and(|e| self.next >= e) {
            return None;
        }
        let w = ((self.next - self.start) % self.receivers.len() as u64) as usize;
        let item = match self.receivers[w].recv() {
            Ok(item) => item,
            Err(_) => Err(DataError::Worker(format!(
                "worker {w} stopped before producing sample {}",
                self.next
            ))),
        };
        self.next += 1;
        Some(item)
    }
}

impl<T> Drop for Prefetcher<T> {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        // Dropping the receivers makes any blocked send fail.
        self.receivers.clear();
        for h in self.handles.drain(..) {
            let _ = h.join();
        }
    }
}

/// Batches of a [`Prefetcher`].
pub struct Batches<T> {
    inner: Prefetcher<T>,
    size: usize,
}

impl<T: Send + 'static> Iterator for Batches<T> {
    type Item = Result<Vec<T>, DataError>;

    fn next(&mut self) -> Option<Self::Item> {
        let mut batch = Vec::with_capacity(self.size);
        for _ in 0..self.size {
            match self.inner.next() {
                Some(Ok(item)) => batch.push(item),
                Some(Err(e)) => return Some(Err(e)),
                None => break,
            }
        }
        (!batch.is_empty()).then_some(Ok(batch))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn order_is_the_index_order_for_any_worker_count() {
        for workers in [1, 2, 3, 7] {
            let items: Vec<u64> = Prefetcher::new(5, Some(20), workers, 2, |i| {
                std::thread::sleep(std::time::Duration::from_micros((i * 37 % 11) * 100));
                Ok(i * i)
            })
            .map(|r| r.unwrap())
            .collect();
            assert_eq!(items, (5..25).map(|i| i * i).collect::<Vec<_>>());
        }
        let batches: Vec<Vec<u64>> = Prefetcher::new(0, Some(7), 2, 1, Ok)
            .batches(3)
            .map(|b| b.unwrap())
            .collect();
        assert_eq!(batches, vec![vec![0, 1, 2], vec![3, 4, 5], vec![6]]);
    }

    #[test]
    fn errors_and_panics_surface_as_items_and_drop_stops_endless_streams() {
        let items: Vec<Result<u64, DataError>> = Prefetcher::new(0, Some(4), 2, 1, |i| {
            if i == 2 {
                panic!("boom");
            }
            if i == 3 {
                Err(DataError::Sample {
                    index: i,
                    message: "nope".into(),
                })
            } else {
                Ok(i)
            }
        })
        .collect();
        assert!(items[0].is_ok() && items[1].is_ok() && items[2].is_err() && items[3].is_err());
        let mut endless = Prefetcher::new(0, None, 3, 4, Ok);
        assert_eq!(endless.next().unwrap().unwrap(), 0);
        drop(endless); // must not hang
    }
}
