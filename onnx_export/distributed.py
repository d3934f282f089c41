"""Training beyond one process: every trainer of ``onnx_export`` runs unchanged under ``torchrun``.

    torchrun --standalone --nproc_per_node 4 -m onnx_export.layering train --size tiny ... --out cache/runs/x

One scheme serves all of them (data parallelism, as DistributedDataParallel does it):

- every process draws the *whole* batch from the same seed, so the random generators stay in step;
- each process computes the loss of its equal share of the batch (``Processes.rows``), a mean over that
  share, so the mean over processes is the whole batch's loss;
- after ``backward`` the gradients are averaged over the processes (``Processes.average_gradients``,
  one all-reduce of all of them), before clipping and the optimiser step;
- process 0 logs, evaluates and writes checkpoints and models; the others read the same checkpoint
  when a run resumes.

N processes therefore follow the one-process run step for step (``tests/training/test_distributed.py``
checks each trainer). The process group is gloo: the trainers keep their tensors on the CPU (NCCL
reduces CUDA tensors only, so a CUDA machine would need the trainers moved to the device first). Outside
``torchrun`` (``WORLD_SIZE`` unset or 1) every method is a no-op and nothing is initialised.
"""

from __future__ import annotations

import atexit
import os
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Processes:
    """This process's place in the run: ``rank`` of ``world`` processes."""

    rank: int = 0
    world: int = 1

    @property
    def main(self) -> bool:
        """True for the process that logs, evaluates and writes files."""
        return self.rank == 0

    def rows(self, n: int, what: str = "--batch") -> slice:
        """This process's share of a batch of ``n`` rows drawn by every process alike."""
        if n % self.world:
            raise ValueError(f"{what} gives batches of {n}: it must be a multiple of the {self.world} processes")
        k = n // self.world
        return slice(self.rank * k, (self.rank + 1) * k)

    def average_gradients(self, params) -> None:
        """Replace each parameter's gradient by its mean over the processes (one all-reduce in all)."""
        if self.world == 1:
            return
        ps = [p for p in params if p.grad is not None]
        flat = torch.cat([p.grad.reshape(-1) for p in ps])
        torch.distributed.all_reduce(flat)
        flat /= self.world
        i = 0
        for p in ps:
            n = p.grad.numel()
            p.grad.copy_(flat[i : i + n].view_as(p.grad))
            i += n

    def total(self, x: torch.Tensor) -> torch.Tensor:
        """Sum of a (detached) tensor over the processes."""
        x = x.detach().clone()
        if self.world > 1:
            torch.distributed.all_reduce(x)
        return x

    def mean(self, x: torch.Tensor) -> float:
        """Mean over the processes of a scalar tensor (a loss to log)."""
        return float(self.total(x)) / self.world


ONE_PROCESS = Processes()


def processes() -> Processes:
    """The process group of ``torchrun`` (``WORLD_SIZE`` > 1), initialised on first use, else one process."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return ONE_PROCESS
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("gloo")
        atexit.register(_leave_group)
    return Processes(dist.get_rank(), dist.get_world_size())


def _leave_group() -> None:
    """At exit, wait for the other processes (process 0 ends later: it evaluates and writes) and destroy
    the group while the interpreter is whole. A process that leaves with its gloo connections open while
    a peer still uses them can abort ("terminate called without an active exception", SIGABRT) and
    fail a run that had finished. The wait is bounded, so a process that failed does not hang here."""
    from datetime import timedelta

    import torch.distributed as dist

    if not dist.is_initialized():
        return
    try:
        dist.monitored_barrier(timeout=timedelta(seconds=120))
    except RuntimeError:
        pass  # a peer failed or left: nothing to wait for
    dist.destroy_process_group()


def quiet_unless_main(log, procs: Processes):
    """``log`` for process 0, a function that says nothing for the others."""
    return log if procs.main else (lambda s: None)
