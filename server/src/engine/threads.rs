//! Two independent libtorch computations at once, each on one intra-op thread.
//!
//! Module map: [`side_by_side`] (the only entry point).
//!
//! Why: Algorithm 1 runs two frozen diffusion models on the same batch, and they do not depend
//! on each other. Run one after the other with libtorch's intra-op parallelism (OpenMP, one
//! thread per core), every convolution, GroupNorm and Mish of a small-batch TemporalUnet is a
//! fork and a join of the thread team, and the team's threads spin at each join while the
//! slowest finishes (on a shared machine, while a descheduled partner waits for a core). Run
//! side by side, one model per thread with one intra-op thread each, the two halves need no
//! synchronisation until both are done (profiled in BENCHMARKS.md, "Training against
//! `torch.compile`": this is what moved relreward's Algorithm 1 step past PyTorch eager's).
//!
//! libtorch's thread count is per thread (OpenMP's `nthreads-var`, MKL's local setting) but
//! `set_num_threads` also writes a process-wide default that threads read when they first use
//! libtorch. [`side_by_side`] narrows the calling thread and a fresh helper thread to one
//! intra-op thread each and restores the default at once (from a throwaway thread, so the
//! caller stays narrow): the narrowed default is visible for about two thread starts per
//! call. A thread of the process that first uses libtorch inside that window keeps one
//! intra-op thread (slower, never wrong). Only with `engine.intra_op_threads` >= 2 (the
//! default is 1, where this is sequential and touches nothing).

use std::sync::mpsc;

use crate::error::{Error, Result};

/// Runs `here` on the calling thread and `there` on a helper thread at the same time, each
/// with one intra-op thread, when libtorch has at least two intra-op threads and `parallel` is
/// true; otherwise one after the other on the calling thread with the configured threads (the
/// results are the same either way, up to the order of floating-point reductions). Grad mode
/// is per thread in libtorch: `there` runs with grad mode off, as the frozen models' passes
/// are meant to.
pub fn side_by_side<A, B>(
    parallel: bool,
    here: impl FnOnce() -> Result<A>,
    there: impl FnOnce() -> Result<B> + Send,
) -> Result<(A, B)>
where
    B: Send,
{
    let width = tch::get_num_threads();
    if !parallel || width < 2 {
        let a = here()?;
        let b = tch::no_grad(there)?;
        return Ok((a, b));
    }
    std::thread::scope(|scope| {
        tch::set_num_threads(1);
        let (ready, started) = mpsc::sync_channel::<()>(1);
        let helper = std::thread::Builder::new().name("side-by-side".into()).spawn_scoped(scope, move || {
            // The first libtorch call on a new thread takes the process default (now 1).
            let _ = tch::get_num_threads();
            let _ = ready.send(());
            tch::no_grad(there)
        });
        match helper {
            Ok(helper) => {
                let _ = started.recv();
                restore_default(scope, width);
                let a = here();
                let b = helper.join().map_err(|_| Error::internal("side_by_side", "the helper thread panicked"));
                tch::set_num_threads(width);
                Ok((a?, b??))
            }
            Err(e) => {
                tch::set_num_threads(width);
                Err(Error::internal("side_by_side: spawning the helper thread", e))
            }
        }
    })
}

/// Sets libtorch's process-wide default back to `width` from a throwaway thread (a call here
/// would also widen the calling thread).
fn restore_default<'scope>(scope: &'scope std::thread::Scope<'scope, '_>, width: i32) {
    match std::thread::Builder::new().spawn_scoped(scope, move || tch::set_num_threads(width)) {
        Ok(h) => {
            let _ = h.join();
        }
        // No thread to spare: widen from here; the caller then runs its half on `width`
        // threads beside the helper (slower, never wrong).
        Err(_) => tch::set_num_threads(width),
    }
}

#[cfg(test)]
mod tests {
    use tch::{Kind, Tensor};

    use super::*;

    #[test]
    fn side_by_side_computes_what_sequential_computes_and_restores_the_width() {
        let width = tch::get_num_threads();
        let x = Tensor::randn([64, 32, 16], (Kind::Float, tch::Device::Cpu));
        let w = Tensor::randn([32, 32, 5], (Kind::Float, tch::Device::Cpu));
        let f = |x: &Tensor| -> Result<Tensor> { Ok(x.conv1d(&w, None::<Tensor>, [1], [2], [1], 1).mish()) };
        let (x1, x2) = (x.shallow_clone(), x.shallow_clone());
        // A parameter that wants gradients: the helper's output must not track them.
        let w2 = w.detach().copy().set_requires_grad(true);
        for parallel in [true, false] {
            let (x2, w2) = (x2.shallow_clone(), w2.shallow_clone());
            let (a, (b, tracked)) = side_by_side(
                parallel,
                || f(&x1),
                move || {
                    let y = x2.conv1d(&w2, None::<Tensor>, [1], [2], [1], 1).mish();
                    let tracked = y.requires_grad();
                    Ok((y, tracked))
                },
            )
            .expect("side by side");
            assert!(a.allclose(&b, 1e-5, 1e-5, false), "parallel {parallel}");
            assert!(!tracked, "the helper runs under no-grad");
            assert_eq!(tch::get_num_threads(), width, "the caller's width is restored");
        }
        // (That a thread starting afterwards gets the configured default is not asserted here:
        // other tests of this process run side_by_side concurrently, and a thread that starts
        // inside one of their windows takes one thread, as the module documentation says.)
        // Errors from either side come back as errors.
        let e = side_by_side(true, || Ok(()), || -> Result<()> { Err(Error::invalid("there")) }).expect_err("err");
        assert!(e.to_string().contains("there"));
    }
}
