"""The compressed BTF of a run (:mod:`pipeline.btf.compressed`): the cached ``export`` stage
(:func:`export_stage` for Neural BTF and clustered, :func:`export_linear_stage` for PCA),
and the file logged to MLflow with an MLflow pyfunc model around it."""

from __future__ import annotations

import tempfile
import warnings
from importlib import metadata as package_metadata
from pathlib import Path

import mlflow
import mlflow.pyfunc  # the base class of the logged model (CompressedBTFModel)
import pandas as pd  # mlflow imports it too; the pyfunc model's predict is typed with it

from pipeline.btf.compressed import (
    FILE_NAME,
    QUERY_COLUMNS,
    RGB_COLUMNS,
    TABLE1_PARTS,
    header_bytes,
    load_compressed,
    payload_bytes,
    stored_parts,
    support_bytes,
    write_compressed,
    write_compressed_pca,
)
from pipeline.btf.models import model_of
from pipeline.core.cache import Entry
from pipeline.core.run_log import RunLog
from pipeline.core.stage import Context, plain_settings


def export_stage(
    ctx: Context, cropped: Entry, prep: Entry, trained: Entry, evaluated: Entry
) -> Entry:
    """Write the run's compressed BTF, ``btf.safetensors``, into a cache entry.

    Its tensors are Table 1's bytes exactly (checked against the evaluate stage's
    ``bytes_total``); the per-texel scale is the one the evaluate stage fitted.
    """
    cfg = ctx.cfg
    clustered = model_of(cfg).clusters
    k = cfg.model.k if clustered else None
    settings = {
        "sizes": plain_settings(cfg.btf.sizes),
        "method": cfg.model.name,
        "k": k,
        "crop": plain_settings(cfg.btf.crop),
        "dataset": cfg.dataset.name,
    }
    inputs = {"crop": cropped, "preprocess": prep, "train": trained, "evaluate": evaluated}

    def compute(folder: Path) -> dict:
        from pipeline.btf.model import load_decoder

        has_scale = evaluated.file("texel_scale.npy").is_file()
        path = write_compressed(
            folder / FILE_NAME,
            load_decoder(trained.file("decoder.pt")),
            trained.array("latents", mmap=False),
            prep.json("alpha"),
            **_placement(cfg),
            method=cfg.model.name,
            k=k,
            latent_of_texel=trained.array("latent_of_texel", mmap=False) if clustered else None,
            texel_scale=evaluated.array("texel_scale", mmap=False) if has_scale else None,
            texel_scale_mode=evaluated.manifest["settings"]["texel_scale"],
            weight_dtype=settings["sizes"]["weight_dtype"],
            list_dtype=settings["sizes"]["list_dtype"],
            extra_dtype=settings["sizes"]["extra_dtype"],
        )
        return _checked_against_table1(path, evaluated.json("metrics"))

    return ctx.run("export", settings, inputs, compute, version="2")


def export_linear_stage(ctx: Context, cropped: Entry, prep: Entry, fitted: Entry) -> Entry:
    """Write the PCA baseline's compressed file, ``btf.safetensors`` (method ``pca``), into
    a cache entry: the linear stage's arrays as stored (its tensors are the linear stage's
    ``bytes_total``, checked) and the crop's direction pairs, which the file needs to be
    evaluated between them as the renderer does."""
    settings = {"crop": plain_settings(ctx.cfg.btf.crop), "dataset": ctx.cfg.dataset.name}
    inputs = {"crop": cropped, "preprocess": prep, "linear": fitted}

    def compute(folder: Path) -> dict:
        coefficients = fitted.array("coefficients", mmap=False)
        path = write_compressed_pca(
            folder / FILE_NAME,
            fitted.array("mean", mmap=False),
            fitted.array("basis", mmap=False),
            coefficients,
            prep.json("alpha"),
            measured_directions=cropped.array("directions", mmap=False),
            **_placement(ctx.cfg),
            weight_dtype=str(coefficients.dtype),  # the linear stage stores model.dtype
        )
        return _checked_against_table1(path, fitted.json("metrics"))

    return ctx.run("export", settings, inputs, compute, version="1")


def _placement(cfg) -> dict:
    """``crop_size``, ``crop_offset`` and ``dataset``, as a compressed file records them."""
    crop = plain_settings(cfg.btf.crop)
    size, offset = crop["size"], tuple(crop["offset"])
    return {"crop_size": (size, size), "crop_offset": offset, "dataset": cfg.dataset.name}


def _checked_against_table1(path: Path, table1: dict) -> dict:
    """The export stage's summary of the file at ``path``, after checking that its
    tensors are Table 1's bytes (``table1``: the run's ``bytes_*`` metrics), part by part;
    RuntimeError when they differ (the stage's size accounting and the format disagree).
    """
    payload, parts = payload_bytes(path), stored_parts(path)
    counted = {part: table1[f"bytes_{part}"] for part in TABLE1_PARTS}
    stored = {part: parts.get(part, {"bytes": 0})["bytes"] for part in TABLE1_PARTS}
    if payload != table1["bytes_total"] or stored != counted:
        raise RuntimeError(
            f"{path} holds {payload} bytes of tensors ({stored}), but "
            f"Table 1 counts {table1['bytes_total']} ({counted}): "
            f"the size accounting and the format disagree"
        )
    return {
        "bytes_payload": payload,
        "bytes_support": support_bytes(path),
        "bytes_header": header_bytes(path),
        "bytes_file": path.stat().st_size,
        "stored_as": {part: found["dtype"] for part, found in parts.items()},
    }


def log_compressed(log: RunLog, entry: Entry) -> None:
    """Log the export stage's file to the job's MLflow run as ``compressed/btf.safetensors``
    (the cached file as it is: equal models log equal bytes) and an
    MLflow pyfunc model ``compressed_btf`` around it::

        mlflow.set_tracking_uri(pipeline.tracking_uri(runs))  # the jobs' paths.runs
        model = mlflow.pyfunc.load_model(f"runs:/{run_id}/compressed_btf")
        rgb = model.predict(df)   # columns texel, theta_light, phi_light, theta_view,
                                  # phi_view (one query a row) -> columns R, G, B

    The model needs this package (``pipeline``) importable where it is loaded.
    """
    path = entry.file(FILE_NAME)
    log.file(path, "compressed")
    if not log.on:
        return
    with tempfile.TemporaryDirectory() as tmp:
        # "Models from code": the model is this short script, not a pickled object.
        code = Path(tmp) / "compressed_btf_model.py"
        code.write_text(MODEL_CODE)
        with warnings.catch_warnings():
            # The signature says what a query is; an example would only slow logging.
            warnings.filterwarnings("ignore", ".*An input example was not provided")
            mlflow.pyfunc.log_model(
                name="compressed_btf",
                python_model=str(code),
                artifacts={"btf": str(path)},
                signature=query_signature(),
                # Given, so that MLflow does not load the model in a subprocess to infer
                # them (it still scans the installed packages once per process). scipy:
                # a PCA file's interpolation.
                pip_requirements=[
                    f"{name}=={package_metadata.version(name)}"
                    for name in ("torch", "safetensors", "numpy", "scipy", "pandas")
                ],
            )


MODEL_CODE = """\
# The compressed BTF of pipeline.btf.compressed as an MLflow pyfunc model.
import mlflow

from pipeline.btf.export import CompressedBTFModel

mlflow.models.set_model(CompressedBTFModel())
"""


def query_signature():
    """The pyfunc model's signature: one query a row in, one RGB a row out."""
    from mlflow.models import ModelSignature
    from mlflow.types import ColSpec, Schema

    queries = [ColSpec("long", "texel")] + [ColSpec("double", name) for name in QUERY_COLUMNS[1:]]
    outputs = Schema([ColSpec("float", name) for name in RGB_COLUMNS])
    return ModelSignature(inputs=Schema(queries), outputs=outputs)


class CompressedBTFModel(mlflow.pyfunc.PythonModel):
    """The MLflow pyfunc face of a compressed BTF (:func:`log_compressed`)."""

    def load_context(self, context) -> None:
        self.btf = load_compressed(context.artifacts["btf"])

    def predict(self, context, model_input: pd.DataFrame, params=None) -> pd.DataFrame:
        """DataFrame with columns texel, theta_light, phi_light, theta_view, phi_view
        (radians) -> DataFrame with columns R, G, B (linear RGB, float32)."""
        missing = [c for c in QUERY_COLUMNS if c not in model_input.columns]
        if missing:
            raise ValueError(f"the query lacks columns {missing}; it needs {list(QUERY_COLUMNS)}")
        rgb = self.btf.query_pairs(
            model_input["texel"].to_numpy(), model_input[list(QUERY_COLUMNS[1:])].to_numpy()
        )
        return pd.DataFrame(rgb, columns=list(RGB_COLUMNS), index=model_input.index)
