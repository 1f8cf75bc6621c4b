//! Execution resources of multi-threaded steps: the thread pool and the partition of
//! nodes and elements (`crate::parallel`).

use std::sync::Arc;

use super::FemSystem;
use crate::FemError;
use crate::parallel::Partition;

/// Thread pool and partition of a [`FemSystem`] ([`crate::StepParams::threads`]).
#[derive(Clone, Debug)]
pub(super) struct Execution {
    /// Thread pool of multi-threaded steps, built on first use.
    pub(super) pool: Option<Arc<rayon::ThreadPool>>,
    /// Threads of the step in progress (1 outside multi-threaded steps).
    pub(super) threads: usize,
    /// Split of nodes and elements for `threads` (rebuilt with the assembly order).
    pub(super) partition: Option<Partition>,
}

impl Default for Execution {
    fn default() -> Self {
        Self {
            pool: None,
            threads: 1,
            partition: None,
        }
    }
}

impl FemSystem {
    /// The partition, when the step in progress runs on several threads.
    pub(super) fn active_partition(&self) -> Option<&Partition> {
        self.exec
            .partition
            .as_ref()
            .filter(|part| self.exec.threads > 1 && part.threads == self.exec.threads)
    }

    /// The pool for a step on `threads` threads: the one kept from earlier steps, or a new
    /// one (kept for the next steps).
    pub(super) fn thread_pool(
        &mut self,
        threads: usize,
    ) -> Result<Arc<rayon::ThreadPool>, FemError> {
        Ok(match &self.exec.pool {
            Some(pool) if pool.current_num_threads() == threads => pool.clone(),
            _ => {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .thread_name(|i| format!("cosurg-fem-{i}"))
                    .build()
                    .map_err(|e| FemError::BadParameter(format!("{} FEM threads: {e}", threads)))?;
                let pool = Arc::new(pool);
                self.exec.pool = Some(pool.clone());
                pool
            }
        })
    }
}
