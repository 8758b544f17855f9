"""The loops of ``python -m benchmarks.train`` that are timed in a child process of their own.

libgomp reads ``GOMP_SPINCOUNT`` once, when torch loads, so the default training path
(libgomp's defaults) and the opt-in tuned one (:data:`TUNED`) can only be compared in
separate processes; the plain autograd loops run in one too, as a user's own script would.
Each child starts without the parent's OpenMP spin settings (``GOMP_SPINCOUNT``,
``OMP_WAIT_POLICY``) in its environment, sets the tuned spin count, when asked to, before
it imports torch (:func:`pipeline.btf.fast.tuning.set_omp_spin_count`, as a training job
does), then builds its loop and times it each time the parent writes ``run`` on its stdin,
answering ``seconds S`` on its stdout. No torch at this module's top: the child imports it
only after the spin count is set. The child finds this module from any working directory:
its ``PYTHONPATH`` starts with the checkout (:func:`benchmarks.child_env`).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

from benchmarks import child_env

# The opt-in tuning the bench quotes against the defaults (train.* in conf/train/default.yaml).
TUNED = {"keep_awake": True, "omp_spin_count": 30_000, "reuse_freed_memory": True}
LOOPS = ("naive", "decoder_naive", "train")
# Environment variables that set libgomp's spin-waiting; a child starts without them.
OPENMP_SPIN_VARIABLES = ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")


class Isolated:
    """One loop timed in a child process (``loop``: ``naive``, ``decoder_naive``, or
    ``train``, the pipeline's training loop at the paper's batch with ``train.backend``
    ``backend``, with the opt-in tuning when ``tuned``). Calling it runs ``steps`` steps
    there and returns their seconds, like the callables of the loops the bench runs in its
    own process."""

    def __init__(
        self,
        loop: str,
        steps: int,
        threads: int,
        tuned: bool = False,
        precision: str = "float32",
        backend: str = "fused",
    ):
        env = {k: v for k, v in os.environ.items() if k not in OPENMP_SPIN_VARIABLES}
        command = [
            sys.executable,
            "-m",
            "benchmarks.train_child",
            loop,
            "--steps",
            str(steps),
            "--threads",
            str(threads),
            "--precision",
            precision,
            "--backend",
            backend,
        ]
        if tuned:
            command.append("--tuned")
        self.process = subprocess.Popen(
            command, env=child_env(env), text=True, stdin=subprocess.PIPE, stdout=subprocess.PIPE
        )

    def __call__(self) -> float:
        self.process.stdin.write("run\n")
        self.process.stdin.flush()
        while line := self.process.stdout.readline():
            if line.startswith("seconds "):
                return float(line.split()[1])
        raise RuntimeError(f"the bench's child process ended (exit {self.process.wait()})")

    def close(self) -> None:
        self.process.stdin.close()
        self.process.wait()


def main(argv=None) -> None:
    """The child's side of :class:`Isolated`."""
    parser = argparse.ArgumentParser(description="a loop of python -m benchmarks.train")
    parser.add_argument("loop", choices=LOOPS)
    parser.add_argument("--steps", type=int, required=True)
    parser.add_argument("--threads", type=int, required=True)
    parser.add_argument("--precision", default="float32")
    parser.add_argument("--backend", default="fused")
    parser.add_argument("--tuned", action="store_true")
    args = parser.parse_args(argv)
    if args.tuned:
        if "torch" in sys.modules:
            raise RuntimeError("torch is loaded already: GOMP_SPINCOUNT would have no effect")
        from pipeline.btf.fast.tuning import set_omp_spin_count

        set_omp_spin_count(TUNED["omp_spin_count"])
    import torch

    from benchmarks import train_loops as loops

    torch.set_num_threads(args.threads)
    if args.loop == "naive":
        run = loops.naive_training(args.steps, loops.paper_channels())
    elif args.loop == "decoder_naive":
        run = loops.decoder_training(False, args.steps, args.threads)
    else:
        run = loops.pipeline_training(
            5,
            -1,
            args.steps,
            loops.paper_channels(),
            args.threads,
            precision=args.precision,
            backend=args.backend,
            tuning=TUNED if args.tuned else None,
        )
    for _ in sys.stdin:
        print(f"seconds {run()!r}", flush=True)


if __name__ == "__main__":
    main()
