//! How the worker's allocator treats memory the simulators free.
//!
//! Building an environment is mostly memory: a pybullet connection allocates and zeroes large buffers (its
//! command stream, its software renderer's images), tens of megabytes per environment. glibc serves allocations
//! that large with their own `mmap` and gives them back to the kernel with `munmap` when they are freed, so the next
//! environment's zeroing touches fresh pages and takes one page fault per 4 KiB: on a scoring job, which builds a
//! session's environments and closes them when it ends, most of the CPU time of building went to those faults
//! (`bench/score.sh`, the building column). Serving those sizes from the heap and keeping what is freed there lets
//! the next environments reuse pages already mapped. The cost is resident memory: a worker keeps the most its
//! environments ever held until it exits, which is what it needs again for its next sessions.
//!
//! The environments compute the same numbers either way (where an allocation lives changes no value the simulators
//! read; `scripts/rescore.py` compares scored episodes across builds).

/// Allocations up to this size come from the heap (glibc's largest allowed value for `M_MMAP_THRESHOLD`).
const HEAP_UP_TO_BYTES: i32 = 32 << 20;

/// Freed memory at the top of a heap is returned to the kernel only beyond this much.
const KEEP_FREED_BYTES: i32 = 256 << 20;

/// Sets the allocator as described above. Call in `main` before any simulator is loaded (after logging starts, so
/// a refusal is logged): the settings hold for every thread.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt only changes glibc's allocator parameters (it takes the arenas' locks itself).
        let set = unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, HEAP_UP_TO_BYTES) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, KEEP_FREED_BYTES) == 1
        };
        if !set {
            tracing::warn!("the allocator refused its settings: environments are built with fresh pages");
        }
    }
}
