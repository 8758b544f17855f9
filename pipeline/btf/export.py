"""The compressed BTF of a run (:mod:`pipeline.btf.compressed`): the cached ``export`` stage,
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
    read_header,
    safetensors_bytes,
    stored_parts,
    write_atomic,
    write_compressed,
)
from pipeline.core.cache import Entry
from pipeline.core.stage import Context, plain_settings


def export_stage(ctx: Context, cropped: Entry, prep: Entry, trained: Entry,
                 evaluated: Entry) -> Entry:
    """Write the run's compressed BTF, ``btf.safetensors``, into a cache entry.

    Its tensors are Table 1's bytes exactly (checked against the evaluate stage's
    ``bytes_total``); the per-texel scale is the one the evaluate stage fitted.
    """
    cfg = ctx.cfg
    method = cfg.method
    clustered = method.name == "clustered"
    settings = {
        "sizes": plain_settings(cfg.btf.sizes),
        "method": method.name,
        "k": method.get("k") if clustered else None,
        "crop": plain_settings(cfg.btf.crop),
        "dataset": cfg.dataset.name,
    }
    inputs = {"crop": cropped, "preprocess": prep, "train": trained, "evaluate": evaluated}

    def compute(folder: Path) -> dict:
        from pipeline.btf.model import load_decoder

        sizes = plain_settings(cfg.btf.sizes)
        crop_settings = plain_settings(cfg.btf.crop)
        has_scale = evaluated.file("texel_scale.npy").is_file()
        path = write_compressed(
            folder / FILE_NAME,
            load_decoder(trained.file("decoder.pt")),
            trained.array("latents", mmap=False),
            prep.json("alpha"),
            crop_size=(crop_settings["size"], crop_settings["size"]),
            crop_offset=tuple(crop_settings["offset"]),
            method=method.name,
            k=method.get("k") if clustered else None,
            dataset=cfg.dataset.name,
            latent_of_texel=trained.array("latent_of_texel", mmap=False) if clustered else None,
            texel_scale=evaluated.array("texel_scale", mmap=False) if has_scale else None,
            texel_scale_mode=evaluated.manifest["settings"]["texel_scale"],
            weight_dtype=sizes["weight_dtype"],
            list_dtype=sizes["list_dtype"],
            extra_dtype=sizes["extra_dtype"],
        )
        payload, table1 = payload_bytes(path), evaluated.json("metrics")
        parts = stored_parts(path)
        counted = {part: table1[f"bytes_{part}"] for part in TABLE1_PARTS}
        stored = {part: parts.get(part, {"bytes": 0})["bytes"] for part in TABLE1_PARTS}
        if payload != table1["bytes_total"] or stored != counted:
            raise RuntimeError(f"{path} holds {payload} bytes of tensors ({stored}), but "
                               f"Table 1 counts {table1['bytes_total']} ({counted}): "
                               f"storage_sizes and the format disagree")
        return {"bytes_payload": payload, "bytes_header": header_bytes(path),
                "bytes_file": path.stat().st_size,
                "stored_as": {part: found["dtype"] for part, found in parts.items()}}

    return ctx.run("export", settings, inputs, compute, version="2")


def log_compressed(entry: Entry, log_model: bool = True) -> None:
    """Log the export stage's file to the active MLflow run as ``compressed/btf.safetensors``
    (its metadata naming the run) and, with ``log_model``, an MLflow pyfunc model
    ``compressed_btf`` around it::

        mlflow.set_tracking_uri(pipeline.tracking_uri(runs))  # the jobs' paths.runs
        model = mlflow.pyfunc.load_model(f"runs:/{run_id}/compressed_btf")
        rgb = model.predict(df)   # columns texel, theta_light, phi_light, theta_view,
                                  # phi_view (one query a row) -> columns R, G, B

    The model needs this package (``pipeline``) importable where it is loaded.
    """
    run_id = mlflow.active_run().info.run_id
    with tempfile.TemporaryDirectory() as tmp:
        stamped = Path(tmp) / FILE_NAME
        _copy_with_run_id(entry.file(FILE_NAME), stamped, run_id)
        mlflow.log_artifact(str(stamped), "compressed")
        if log_model:
            # "Models from code": the model is this short script, not a pickled object.
            code = Path(tmp) / "compressed_btf_model.py"
            code.write_text(MODEL_CODE)
            with warnings.catch_warnings():
                # The signature says what a query is; an example would only slow logging.
                warnings.filterwarnings("ignore", ".*An input example was not provided")
                mlflow.pyfunc.log_model(
                    name="compressed_btf",
                    python_model=str(code),
                    artifacts={"btf": str(stamped)},
                    signature=query_signature(),
                    # Given, so that MLflow does not load the model in a subprocess to infer
                    # them (it still scans the installed packages once per process).
                    pip_requirements=[f"{name}=={package_metadata.version(name)}"
                                      for name in ("torch", "safetensors", "numpy", "pandas")],
                )


MODEL_CODE = """\
# The compressed BTF of pipeline.btf.compressed as an MLflow pyfunc model.
import mlflow

from pipeline.btf.export import CompressedBTFModel

mlflow.models.set_model(CompressedBTFModel())
"""


def _copy_with_run_id(source: Path, target: Path, run_id: str) -> None:
    """The file at ``source`` with ``mlflow_run_id`` added to its metadata (written in the
    fixed order of :func:`pipeline.btf.compressed.safetensors_bytes`)."""
    from safetensors import safe_open

    read_header(source)
    with safe_open(source, framework="numpy") as f:
        meta = dict(f.metadata() or {})
        tensors = {name: f.get_tensor(name) for name in f.keys()}
    write_atomic(target, safetensors_bytes(tensors, {**meta, "mlflow_run_id": run_id}))


def query_signature():
    """The pyfunc model's signature: one query a row in, one RGB a row out."""
    from mlflow.models import ModelSignature
    from mlflow.types import ColSpec, Schema

    inputs = Schema([ColSpec("long", "texel")]
                    + [ColSpec("double", name) for name in QUERY_COLUMNS[1:]])
    return ModelSignature(inputs=inputs,
                          outputs=Schema([ColSpec("float", name) for name in RGB_COLUMNS]))


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
        rgb = self.btf.query_pairs(model_input["texel"].to_numpy(),
                                   model_input[list(QUERY_COLUMNS[1:])].to_numpy())
        return pd.DataFrame(rgb, columns=list(RGB_COLUMNS), index=model_input.index)
