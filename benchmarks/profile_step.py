"""Where a training step's time goes at ``experiment=paper_cpu``'s size, before and after.

    python -m benchmarks.profile_step [threads=[1,2]] [steps=30] [rounds=3]
                                      [setups=before,encoder,after]

times the parts of one training step (N = 6561 directions, the paper's encoder, Adam),
laid out as ``pipeline.btf.train`` runs them: the batch's data (gather and normalize with
numpy), the encoder's forward, the decoder's fused step, the encoder's backward, the
optimizer. Each setup (:data:`SETUPS`) runs in a child process of its own in every round
(glibc's and OpenMP's process-wide state do not carry over from one setup to the next),
the setups in turn within a round, so that a shared machine that slows down affects all
alike; each child also measures the float32 matrix-multiply peak, the yardstick. Printed per
thread count: milliseconds per step of each part (medians over rounds), GFLOP/s and the
share of the peak (the convolutions' and the decoder's products; the pools, batch-norm and
ReLUs are not counted), the process's CPU time per step (all threads; steadier than the
wall clock on a shared machine), the training time a run of the setup's recipe would take
(steps x ms/step) and the ratio of each setup to the first; then one JSON object.

The setups: ``before``, the recipe of 32 ABRDFs x 256 queries with the encoder as autograd
layers (``Encoder.forward_layers``) and glibc's default allocator; ``encoder``, the same
recipe with the encoder's hand-written training step (``Encoder.forward``,
:mod:`pipeline.btf.fast.encoder_step`); ``after``, that encoder with the recipe of
``experiment=paper_cpu`` (``conf/train/cpu.yaml``: its batch, queries, steps and
``reuse_freed_memory``).

Settings are ``key=value`` (:data:`KEYS`; ``--help`` lists them), read before torch is
imported, so that a bad one is answered at once. The children find this module from any
working directory: their ``PYTHONPATH`` starts with the checkout
(:func:`benchmarks.child_env`).
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time
from dataclasses import dataclass, replace

import numpy as np

from benchmarks import child_env
from benchmarks.train_settings import DECODER_MACS
from pipeline.core import cli
from pipeline.core.methods import CONF_DIR, register_schemas
from pipeline.core.settings import Integer, OneOf

N_PAPER = 6561
PARTS = ("data", "encoder_forward", "decoder", "encoder_backward", "optimizer")
# The recipe of conf/train/cpu.yaml before the faster step (the ``before`` setup).
BEFORE_RECIPE = {
    "batch_size": 32,
    "queries_per_abrdf": 256,
    "epochs": 24,
    "epoch_texels": 10000,
    "reuse_freed_memory": False,
}


def cpu_recipe() -> dict:
    """The training recipe of ``experiment=paper_cpu`` (the composed config, as
    ``python -m pipeline experiment=paper_cpu`` would run it), the keys
    :data:`BEFORE_RECIPE` has."""
    from hydra import compose, initialize_config_dir

    register_schemas()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        train = compose(config_name="config", overrides=["experiment=paper_cpu"]).train
    return {key: train[key] for key in BEFORE_RECIPE}


SETUPS = {
    "before": lambda: BEFORE_RECIPE | {"encoder": "layers"},
    "encoder": lambda: BEFORE_RECIPE | {"encoder": "training"},
    "after": lambda: cpu_recipe() | {"encoder": "training"},
}


PROG = "python -m benchmarks.profile_step"


@dataclass(frozen=True)
class ProfileSettings:
    """What to profile; :data:`KEYS` describes each."""

    threads: tuple[int, ...] = (1, 2)
    steps: int = 30
    rounds: int = 3
    setups: tuple[str, ...] = ("before", "encoder", "after")


def _items(value) -> list:
    """A YAML list, a comma-separated string (``1,2``: numbers) or one value, as a list."""
    if isinstance(value, str):
        words = [word.strip() for word in value.split(",") if word.strip()]
        return [int(word) if word.isdigit() else word for word in words]
    return list(value) if isinstance(value, list | tuple) else [value]


@dataclass(frozen=True)
class _OneOrMore:
    """One value that ``item`` accepts, or a non-empty list (or comma-separated string) of
    them."""

    item: Integer | OneOf

    def ok(self, value) -> bool:
        items = _items(value)
        return bool(items) and all(self.item.ok(item) for item in items)

    def __str__(self) -> str:
        return f"{self.item}, or a list of them"


# Each key of the command line: its field, what it may be, and what it sets.
KEYS = {
    "threads": ("threads", _OneOrMore(Integer(1)), "thread counts, each profiled in turn"),
    "steps": ("steps", Integer(1), "timed steps per child"),
    "rounds": ("rounds", Integer(1), "interleaved rounds (the figures are their medians)"),
    "setups": (
        "setups",
        _OneOrMore(OneOf(*SETUPS)),
        f"the setups, the first the baseline; of {', '.join(SETUPS)}",
    ),
}


COMMAND = cli.Command(
    PROG,
    KEYS,
    ProfileSettings,
    "Where a training step's time goes. Settings and their defaults:",
    what="the profiler",
)


def parse(argv: list[str]) -> ProfileSettings:
    """:class:`ProfileSettings` from ``key=value`` arguments (``threads`` and ``setups`` one
    value or a list); raises :class:`~pipeline.core.errors.ConfigError` naming a bad one."""
    settings = COMMAND.parse(argv)
    return replace(
        settings, threads=tuple(_items(settings.threads)), setups=tuple(_items(settings.setups))
    )


def steps_of(recipe: dict) -> int:
    """Training steps of a run of ``recipe`` (``epoch_texels`` fixed, as in cpu.yaml)."""
    return recipe["epochs"] * (recipe["epoch_texels"] // recipe["batch_size"])


def encoder_flops(batch: int, channels=(16, 32, 64), n: int = N_PAPER) -> tuple[float, float]:
    """FLOPs of the encoder's convolutions and fc layer for ``batch`` ABRDFs: forward, and
    backward (weight and input gradients, none for the ABRDFs themselves)."""
    macs, first_input_grad = 0, 0
    length, previous = n, 3
    for i, width in enumerate(channels):
        block = batch * length * width * previous * 3
        macs += block
        if i == 0:
            first_input_grad = block
        length //= 3
        previous = width
    macs += batch * length * previous * 8
    return 2.0 * macs, 2.0 * (2 * macs - first_input_grad)


def decoder_flops(batch: int, queries: int) -> float:
    """FLOPs of the decoder's products, forward and backward (about 3x the forward's)."""
    return 3 * 2.0 * DECODER_MACS * batch * queries


def matmul_peak() -> float:
    """GFLOP/s of a 2048 x 2048 float32 matrix product
    (:func:`benchmarks.train_figures.matmul_peak`, imported here so that this module's top
    level stays free of torch)."""
    from benchmarks import train_figures

    return train_figures.matmul_peak()


def time_steps(
    recipe: dict, threads: int, steps: int, warmup: int = 5, texels: int = 512, seed: int = 0
) -> dict:
    """Mean milliseconds of each part of ``steps`` training steps of ``recipe`` on
    ``threads`` threads, after ``warmup`` steps, on random ABRDFs of ``texels`` texels,
    and the matmul peak measured at the end (``peak_gflops``)."""
    import torch

    from pipeline.btf.fast.fused import Batch, DecoderStep
    from pipeline.btf.fast.tuning import reuse_freed_memory
    from pipeline.btf.model import Decoder, Encoder
    from pipeline.btf.preprocess import fit_normalization

    b, q = recipe["batch_size"], recipe["queries_per_abrdf"]
    rng = np.random.default_rng(seed)
    abrdf = rng.random((max(texels, b), N_PAPER, 3), dtype=np.float32)
    norm = fit_normalization(abrdf)
    torch.manual_seed(seed)
    encoder, decoder = Encoder(N_PAPER), Decoder()
    forward = encoder.forward if recipe["encoder"] == "training" else encoder.forward_layers
    optimizer = torch.optim.Adam(
        list(encoder.parameters()) + list(decoder.parameters()), lr=1e-4, fused=True
    )
    features = torch.from_numpy(rng.random((N_PAPER, 4), dtype=np.float32) * 2 - 1)
    step_fn = DecoderStep(decoder, features, workers=threads)
    totals = dict.fromkeys(PARTS, 0.0)
    cpu_totals = dict.fromkeys(PARTS, 0.0)

    def step(record: bool) -> None:
        clock, cpu = [time.perf_counter()], [time.process_time()]
        texel_rows = np.sort(rng.choice(abrdf.shape[0], b, replace=False))
        inputs = torch.from_numpy(norm.encoder_input(abrdf[texel_rows])).permute(0, 2, 1)
        queries = rng.integers(0, N_PAPER, size=(b, q))
        target = norm.target(np.take_along_axis(abrdf[texel_rows], queries[:, :, None], 1))
        batch = (torch.from_numpy(queries), torch.from_numpy(target))
        clock.append(time.perf_counter())
        cpu.append(time.process_time())
        torch.set_num_threads(threads)
        latents = forward(inputs)
        clock.append(time.perf_counter())
        cpu.append(time.process_time())
        torch.set_num_threads(1)
        grads = step_fn(Batch(latents, *batch))
        clock.append(time.perf_counter())
        cpu.append(time.process_time())
        torch.set_num_threads(threads)
        optimizer.zero_grad(set_to_none=True)
        step_fn.assign(grads)
        latents.backward(grads.latents)
        clock.append(time.perf_counter())
        cpu.append(time.process_time())
        optimizer.step()
        clock.append(time.perf_counter())
        cpu.append(time.process_time())
        if record:
            for part, start, stop in zip(PARTS, clock[:-1], clock[1:], strict=True):
                totals[part] += stop - start
            for part, start, stop in zip(PARTS, cpu[:-1], cpu[1:], strict=True):
                cpu_totals[part] += stop - start

    memory = reuse_freed_memory() if recipe["reuse_freed_memory"] else contextlib.nullcontext()
    try:
        with memory:
            for _ in range(warmup):
                step(False)
            for _ in range(steps):
                step(True)
    finally:
        step_fn.close()
    torch.set_num_threads(threads)
    return (
        {part: 1e3 * totals[part] / steps for part in PARTS}
        | {f"cpu_{part}": 1e3 * cpu_totals[part] / steps for part in PARTS}
        | {"peak_gflops": matmul_peak()}
    )


def _child(spec: dict) -> dict:
    """One setup's timing in a fresh process (``--child SPEC``: not a setting, the word
    between this process and its children)."""
    command = [sys.executable, "-m", "benchmarks.profile_step", "--child", json.dumps(spec)]
    done = subprocess.run(command, env=child_env(), capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"the profile of {spec['setup']} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def profile(setups: list[str], threads: int, steps: int, rounds: int) -> dict:
    """Each setup's medians over ``rounds`` interleaved rounds at ``threads`` threads:
    ms per part and per step, FLOP rates, the peak, the projected training time."""
    recipes = {name: SETUPS[name]() for name in setups}
    runs: dict[str, list[dict]] = {name: [] for name in setups}
    for _ in range(rounds):
        for name in setups:
            runs[name].append(
                _child({"setup": name, "recipe": recipes[name], "threads": threads, "steps": steps})
            )
    result = {}
    for name, rows in runs.items():
        recipe = recipes[name]
        b, q = recipe["batch_size"], recipe["queries_per_abrdf"]
        ms = {part: float(np.median([row[part] for row in rows])) for part in PARTS}
        ms["step"] = float(np.median([sum(row[p] for p in PARTS) for row in rows]))
        # CPU time of the process (all its threads): on a shared machine, free of the time
        # spent waiting for a core, so steadier than the wall clock.
        cpu_ms = float(np.median([sum(row[f"cpu_{p}"] for p in PARTS) for row in rows]))
        peak = float(np.median([row["peak_gflops"] for row in rows]))
        enc_fwd, enc_bwd = encoder_flops(b)
        dec = decoder_flops(b, q)
        gflops = {
            "encoder": (enc_fwd + enc_bwd) / (ms["encoder_forward"] + ms["encoder_backward"]) / 1e6,
            "decoder": dec / ms["decoder"] / 1e6,
            "step": (enc_fwd + enc_bwd + dec) / ms["step"] / 1e6,
        }
        result[name] = {
            "recipe": recipe,
            "ms": ms,
            "cpu_ms": cpu_ms,
            "gflops": gflops,
            "peak_gflops": peak,
            "share_of_peak": {k: v / peak for k, v in gflops.items()},
            "steps": steps_of(recipe),
            "training_s": steps_of(recipe) * ms["step"] / 1e3,
        }
    first = result[setups[0]]
    for row in result.values():
        row["step_speedup"] = first["ms"]["step"] / row["ms"]["step"]
        row["training_speedup"] = first["training_s"] / row["training_s"]
        row["cpu_step_speedup"] = first["cpu_ms"] / row["cpu_ms"]
    return result


def print_profile(threads: int, result: dict) -> None:
    names = list(result)
    print(
        f"\n{threads} thread(s); float32 matmul peak "
        + ", ".join(f"{result[n]['peak_gflops']:.0f}" for n in names)
        + " GFLOP/s (medians in each setup's children)"
    )
    print(f"{'ms per step':<18}" + "".join(f"{n:>12}" for n in names))
    for part in (*PARTS, "step"):
        print(f"{part:<18}" + "".join(f"{result[n]['ms'][part]:12.2f}" for n in names))
    print(f"{'cpu ms, step':<18}" + "".join(f"{result[n]['cpu_ms']:12.2f}" for n in names))
    for what in ("encoder", "decoder", "step"):
        print(
            f"{'% of peak, ' + what:<18}"
            + "".join(f"{100 * result[n]['share_of_peak'][what]:11.0f}%" for n in names)
        )
    print(
        f"{'batch x queries':<18}"
        + "".join(
            f"{result[n]['recipe']['batch_size']:>7} x{result[n]['recipe']['queries_per_abrdf']:>4}"
            for n in names
        )
    )
    print(f"{'steps of a run':<18}" + "".join(f"{result[n]['steps']:12d}" for n in names))
    print(f"{'training, s':<18}" + "".join(f"{result[n]['training_s']:12.0f}" for n in names))
    print(
        f"{names[0] + ' / setup':<18}"
        + "".join(f"{result[n]['training_speedup']:11.2f}x" for n in names)
        + "   (training time; per step: "
        + ", ".join(f"{result[n]['step_speedup']:.2f}x" for n in names)
        + "; CPU time per step: "
        + ", ".join(f"{result[n]['cpu_step_speedup']:.2f}x" for n in names)
        + ")"
    )


def main(argv: list[str] | None = None) -> dict:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--child"]:  # one setup's timing, in a process that _child started
        spec = json.loads(argv[1])
        row = time_steps(spec["recipe"], spec["threads"], spec["steps"])
        print(json.dumps(row))
        return row
    settings = COMMAND.parse_args(argv, parse)
    setups = list(settings.setups)
    figures = {}
    for threads in settings.threads:
        figures[str(threads)] = profile(setups, threads, settings.steps, settings.rounds)
        print_profile(threads, figures[str(threads)])
    print(json.dumps(figures))
    return figures


if __name__ == "__main__":
    main()
