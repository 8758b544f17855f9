"""Reproducible experiments for measured-reflectance compression and reconstruction.

One subpackage per method: :mod:`pipeline.btf` (A, Neural BTF with clustering),
:mod:`pipeline.brdf_map` (B, MAP reconstruction of anisotropic BRDFs) and
:mod:`pipeline.fourier` (C, Fourier-series light stacks); :mod:`pipeline.core` holds what
they share and :mod:`pipeline.data` the readers of real file layouts. Importing any of them
changes nothing outside the module.

The entry points a script uses, each loaded on first use (``import pipeline`` stays cheap):

- :func:`load_compressed` (:class:`CompressedBTF`): a compressed BTF file, which answers
  RGB queries (``query``: every texel at every direction pair; ``query_pairs``: one a row).
- :func:`tracking_uri`: the MLflow store of a runs folder (``paths.runs``), for MLflow's
  own API (``mlflow.search_runs``, ``mlflow.pyfunc.load_model``, ``MlflowClient``).
- :func:`build_tables`: the tables and figures of ``python -m pipeline.tables``.
- Readers of real layouts: :func:`load_btf` (UBO2003, UTIA), :func:`load_ubo2014`
  (``.btf``), :func:`load_light_stack` (RTI folder with an ``.lp`` file),
  :func:`read_utia_brdf` and :func:`read_merl_brdf` (measured BRDFs).

A trained model, from a script run in any folder (``runs`` is the jobs' ``paths.runs``)::

    import mlflow
    import pandas as pd

    import pipeline

    runs = "runs"
    mlflow.set_tracking_uri(pipeline.tracking_uri(runs))
    found = mlflow.search_runs(experiment_names=["btf"], filter_string="status = 'FINISHED'",
                               order_by=["start_time DESC"])
    run_id = found.loc[found["params.model.name"] == "clustered", "run_id"].iloc[0]

    # The MLflow pyfunc model: one query a row (radians) -> columns R, G, B (linear RGB).
    model = mlflow.pyfunc.load_model(f"runs:/{run_id}/compressed_btf")
    queries = pd.DataFrame({"texel": [0, 1], "theta_light": [0.5, 0.5], "phi_light": [0.0, 1.0],
                            "theta_view": [0.3, 0.3], "phi_view": [0.0, 0.0]})
    print(model.predict(queries))

    # The same file without MLflow: decoder, latents and list (numpy, torch, safetensors).
    path = mlflow.artifacts.download_artifacts(run_id=run_id,
                                               artifact_path="compressed/btf.safetensors")
    btf = pipeline.load_compressed(path)
    print(btf.query_pairs(queries["texel"], queries.iloc[:, 1:]))  # the same values
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# name -> module that defines it: imported on first use (PEP 562), not with the package.
_PUBLIC = {
    "load_compressed": "pipeline.btf.compressed",
    "CompressedBTF": "pipeline.btf.compressed",
    "tracking_uri": "pipeline.core.store",
    "build_tables": "pipeline.tables",
    "load_btf": "pipeline.data.btf",
    "load_ubo2014": "pipeline.data.ubo2014",
    "load_light_stack": "pipeline.data.light_stack",
    "read_utia_brdf": "pipeline.data.brdf",
    "read_merl_brdf": "pipeline.data.brdf",
}
__all__ = [  # the keys of _PUBLIC, spelled out for linters and star-imports
    "CompressedBTF",
    "build_tables",
    "load_btf",
    "load_compressed",
    "load_light_stack",
    "load_ubo2014",
    "read_merl_brdf",
    "read_utia_brdf",
    "tracking_uri",
]

if TYPE_CHECKING:  # what editors and type checkers see; at run time __getattr__ loads them
    from pipeline.btf.compressed import CompressedBTF, load_compressed
    from pipeline.core.store import tracking_uri
    from pipeline.data.brdf import read_merl_brdf, read_utia_brdf
    from pipeline.data.btf import load_btf
    from pipeline.data.light_stack import load_light_stack
    from pipeline.data.ubo2014 import load_ubo2014
    from pipeline.tables import build_tables


def __getattr__(name: str):
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # found directly from now on
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
