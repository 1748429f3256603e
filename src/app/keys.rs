//! One submission at a time per `Idempotency-Key`.
//!
//! A retry finds the job its key made before it takes a place in the queue or fills in the
//! latest version ([`super::App`]'s `retried`). Sent at once, copies of one request would
//! all look before any had made the job: each then took a queue place of its own (503 at a
//! nearly full queue) or filled in a version that a geometry update had just made (409, "a
//! different request"). Holding the key from that lookup until the job's record is made
//! lets each copy after the first find the first one's job, as a later retry does.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// Locks by key, each held from a submission's lookup of its key until its job exists.
#[derive(Default)]
pub(super) struct KeyLocks {
    held: Mutex<HashMap<String, Arc<tokio::sync::Mutex<()>>>>,
}

/// A key's lock, released (and forgotten when nobody waits for it) on drop.
pub(super) struct KeyGuard<'a> {
    locks: &'a KeyLocks,
    key: String,
    guard: Option<tokio::sync::OwnedMutexGuard<()>>,
}

impl KeyLocks {
    /// Waits for `key`'s lock.
    pub(super) async fn lock(&self, key: &str) -> KeyGuard<'_> {
        let lock = Arc::clone(self.map().entry(key.to_string()).or_default());
        KeyGuard {
            locks: self,
            key: key.to_string(),
            guard: Some(lock.lock_owned().await),
        }
    }

    fn map(&self) -> std::sync::MutexGuard<'_, HashMap<String, Arc<tokio::sync::Mutex<()>>>> {
        self.held.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Keys with a lock held or awaited.
    #[cfg(test)]
    fn len(&self) -> usize {
        self.map().len()
    }
}

impl Drop for KeyGuard<'_> {
    fn drop(&mut self) {
        drop(self.guard.take());
        let mut map = self.locks.map();
        // Only the map's own reference left: nobody holds or awaits the key. (Waiters take
        // theirs under the map's lock, so none can appear between the count and the
        // removal.)
        if map
            .get(&self.key)
            .is_some_and(|l| Arc::strong_count(l) == 1)
        {
            map.remove(&self.key);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn one_holder_per_key_and_nothing_kept_after() {
        let locks = Arc::new(KeyLocks::default());
        let first = locks.lock("k").await;
        // Another key is not held up.
        drop(locks.lock("other").await);
        let waiter = {
            let locks = Arc::clone(&locks);
            tokio::spawn(async move {
                let _g = locks.lock("k").await;
            })
        };
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        assert!(
            !waiter.is_finished(),
            "a second holder of the same key waits"
        );
        drop(first);
        waiter.await.unwrap();
        assert_eq!(locks.len(), 0, "no key is remembered once released");
    }
}
