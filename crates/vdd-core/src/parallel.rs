//! Independent jobs on a few threads, their results in item order ([`parallel_map`]).
//!
//! The jobs' results never depend on the scheduling as long as each job is seeded by its item
//! (as every job of the workspace is): which thread ran an item is not observable.

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// Runs `f` on every item with up to `workers` threads (work-stealing by index) and returns the
/// results in item order, or the first error in item order. After a failure no new item starts
/// (items already running finish).
///
/// ```
/// let squares = vdd_core::parallel::parallel_map(&[1u64, 2, 3], 2, |&x| Ok::<_, String>(x * x));
/// assert_eq!(squares.unwrap(), [1, 4, 9]);
/// ```
pub fn parallel_map<T: Sync, R: Send, E: Send>(
    items: &[T],
    workers: usize,
    f: impl Fn(&T) -> Result<R, E> + Sync,
) -> Result<Vec<R>, E> {
    let n = items.len();
    let workers = workers.clamp(1, n.max(1));
    if workers == 1 {
        return items.iter().map(&f).collect();
    }
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let slots: Vec<Mutex<Option<Result<R, E>>>> = (0..n).map(|_| Mutex::new(None)).collect();
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| {
                while !failed.load(Ordering::Relaxed) {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    if i >= n {
                        break;
                    }
                    let r = f(&items[i]);
                    if r.is_err() {
                        failed.store(true, Ordering::Relaxed);
                    }
                    *slots[i].lock().unwrap_or_else(|e| e.into_inner()) = Some(r);
                }
            });
        }
    });
    let mut out = Vec::with_capacity(n);
    for (item, slot) in items.iter().zip(slots) {
        match slot.into_inner().unwrap_or_else(|e| e.into_inner()) {
            Some(r) => out.push(r?),
            // Items are claimed in index order, so an item left unstarted comes after the
            // failed one and this is never reached; running it here keeps the function total.
            None => out.push(f(item)?),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parallel_map_keeps_order_and_reports_the_first_error() {
        let items: Vec<u64> = (0..20).collect();
        for workers in [1, 2, 4] {
            let out = parallel_map(&items, workers, |&x| Ok::<_, String>(x * x)).unwrap();
            assert_eq!(out, items.iter().map(|x| x * x).collect::<Vec<_>>());
        }
        let e = parallel_map(&items, 1, |&x| if x >= 3 { Err(format!("bad {x}")) } else { Ok(x) });
        assert_eq!(e.unwrap_err(), "bad 3");
        let e = parallel_map(&items, 3, |&x| if x == 7 { Err("seven".to_owned()) } else { Ok(x) });
        assert_eq!(e.unwrap_err(), "seven");
        assert!(parallel_map(&Vec::<u8>::new(), 2, |&x| Ok::<_, ()>(x)).unwrap().is_empty());
    }
}
