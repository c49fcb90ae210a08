//! One-thread rayon pools, borrowed one per task: the task's parallel work runs on a single
//! thread, so its floating-point results are the same bit for bit whatever the caller's
//! thread count, and at most as many tasks run at once as there are pools.

use std::sync::{Condvar, Mutex};

/// One-thread rayon pools, one per worker of the caller's pool. A decode borrows one, so its
/// tensor work runs on a single thread (bit-identical results whatever the thread count) and
/// at most as many scans are decoded at once as there are pools. (Installing a fresh pool per
/// scan would let the waiting worker pick up further scans, starting all of a batch at once.)
///
/// A pool is handed back by its own thread when the decode ends, never by the waiting caller:
/// a caller that waits for a pool may itself be blocked inside work it picked up meanwhile.
pub struct Pools {
    pools: Vec<rayon::ThreadPool>,
    free: Mutex<Vec<usize>>,
    returned: Condvar,
}

impl Pools {
    /// `n` pools (at least one).
    pub fn new(n: usize) -> Result<Self, rayon::ThreadPoolBuildError> {
        let pools = (0..n.max(1))
            .map(|_| rayon::ThreadPoolBuilder::new().num_threads(1).build())
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Pools {
            free: Mutex::new((0..pools.len()).collect()),
            pools,
            returned: Condvar::new(),
        })
    }

    /// Runs `op` on a free pool's one thread, waiting for one to be free.
    pub fn run<R: Send>(&self, op: impl FnOnce() -> R + Send) -> R {
        let index = {
            let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
            loop {
                if let Some(i) = free.pop() {
                    break i;
                }
                free = self.returned.wait(free).unwrap_or_else(|e| e.into_inner());
            }
        };
        // Runs on the pool's thread when `op` ends (also on a panic).
        struct Release<'a>(&'a Pools, usize);
        impl Drop for Release<'_> {
            fn drop(&mut self) {
                self.0
                    .free
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .push(self.1);
                self.0.returned.notify_one();
            }
        }
        self.pools[index].install(|| {
            let _release = Release(self, index);
            op()
        })
    }
}
