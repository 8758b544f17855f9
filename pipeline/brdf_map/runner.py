"""Method B's chain in the app: data, fit, baselines, evaluation and figures, with the cache.

    brdf_data -> brdf_fit ---------> brdf_evaluate (metrics, figures, reconstruction)
             \\-> brdf_baselines --/

* ``brdf_data``: reads a UTIA or MERL file (``dataset.format``), optionally removes light
  or view polar angles above ``dataset.missing_above_deg``, and stores the samples plus,
  where known, the ground truth. The built-in synthetic BRDF (``dataset=synthetic_brdf``,
  ``root: null``) is first written under ``${paths.data}`` in the UTIA layout with its
  grazing part missing, then read back with the real reader; its generator is the truth.
  On real data with a mask, the removed measured values are the truth.
* ``brdf_fit``: :func:`~pipeline.brdf_map.microfacet_em.fit_microfacet_em` with the settings
  of ``method.*``; stores Theta as ``parameters.json`` (enough to rebuild the BRDF, see
  :func:`load_reconstruction`), d, the objective history.
* ``brdf_baselines``: the same fit with w_u = 0, and Ashikhmin-Shirley least squares.
* ``brdf_evaluate``: RMSE on the measured samples and, where truth exists, on the missing
  ones, for the method and both baselines, the missing ones also split at theta_h =
  ``NEAR_MIRROR_DEG`` (near the mirror direction, where a lobe's peak dominates the error
  and the Dirichlet prior on u has little say, against the rest); the figures of Figs.
  2-8; the reconstruction sampled on the complete UTIA grid (``reconstruction_utia.bin``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from pipeline.brdf_map.ashikhmin_shirley import AshikhminShirleyFit, fit_ashikhmin_shirley
from pipeline.brdf_map.microfacet_em import fit_microfacet_em, fit_without_prior, rmse
from pipeline.brdf_map.microfacet_model import HemisphereGrid, MicrofacetFit, MixtureParams
from pipeline.brdf_map.settings import em_settings
from pipeline.brdf_map.synthetic import SyntheticAnisotropicBRDF, write_synthetic_utia_brdf
from pipeline.core.cache import Entry, canonical_json, save_arrays, save_json
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.report import save_figure
from pipeline.core.stage import Context, plain_settings
from pipeline.data import brdf as brdf_io

log = logging.getLogger(__name__)


READERS = {"utia": brdf_io.read_utia_brdf, "merl": brdf_io.read_merl_brdf}
NEAR_MIRROR_DEG = 10.0  # missing samples with theta_h below this are "near the mirror direction"


# --------------------------------------------------------------------------- data


def _source(cfg) -> tuple[Path, SyntheticAnisotropicBRDF | None]:
    """The file to read and, for the built-in BRDF, its generator (written on first use)."""
    ds = cfg.dataset
    if ds.get("root") is None and ds.get("synthetic") is not None:
        gen = plain_settings(ds.synthetic)
        for name in ("specular_scale", "diffuse_albedo"):
            gen[name] = tuple(gen[name])
        truth = SyntheticAnisotropicBRDF(**gen)
        tag = canonical_json({"gen": gen, "missing_above_deg": ds.missing_above_deg})
        digest = hashlib.sha256(tag.encode()).hexdigest()[:10]
        path = Path(cfg.paths.data) / f"synthetic_brdf-utia-{digest}.bin"
        if not path.is_file():  # written atomically: a concurrent job sees all of it or none
            log.info("generating the built-in synthetic BRDF into %s", path)
            write_synthetic_utia_brdf(path, truth, ds.missing_above_deg)
        return path.resolve(), truth
    if ds.get("root") is None:
        raise ConfigError(f"dataset={ds.name} needs dataset.root=/path/to/the/file")
    path = Path(str(ds.root)).expanduser().resolve()
    if not path.is_file():
        raise DataError(f"BRDF file {path} does not exist or is not a file")
    return path, None


def data_stage(ctx: Context) -> Entry:
    """Read (or generate) the BRDF, apply the mask, store samples and any ground truth."""
    ds = ctx.cfg.dataset
    if ds.format not in READERS:
        raise ConfigError(f"dataset.format={ds.format!r} is not one of {sorted(READERS)}")
    path, truth_model = _source(ctx.cfg)
    stat = path.stat()
    settings = {
        "format": ds.format,
        "path": str(path),
        "fingerprint": {"bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns},
        "missing_above_deg": ds.missing_above_deg,
        "synthetic": None if truth_model is None else asdict(truth_model),
    }

    def compute(folder: Path) -> dict:
        data = READERS[ds.format](path)
        in_file = data.measured
        if ds.missing_above_deg is not None:
            data = brdf_io.missing_mask_by_polar_angle(data, float(ds.missing_above_deg))
        arrays = {
            "reflectance": data.reflectance,
            "light": data.light,
            "view": data.view,
            "measured": data.measured,
        }
        if truth_model is not None:
            arrays["truth"] = truth_model.evaluate(data.light, data.view)
            arrays["truth_known"] = np.ones(data.n_samples, bool)
        elif ds.missing_above_deg is not None:
            arrays["truth"], arrays["truth_known"] = data.reflectance, in_file
        save_arrays(folder, **arrays)
        missing = brdf_io.above_horizon(data.light, data.view) & ~data.measured
        return {
            "n_samples": data.n_samples,
            "n_measured": int(data.measured.sum()),
            "n_missing": int(missing.sum()),
            "ground_truth": "truth" in arrays,
        }

    # Version 2: the MERL reader places each entry at its own half-vector azimuth (phi_h = 0
    # before), so MERL samples cached by version 1 are stale.
    return ctx.run("brdf_data", settings, {}, compute, version="2")


def measured_brdf(data: Entry) -> brdf_io.MeasuredBRDF:
    """The stage's samples as a MeasuredBRDF (after the mask)."""
    return brdf_io.MeasuredBRDF(
        *(data.array(n, mmap=False) for n in ("reflectance", "light", "view", "measured")),
        source=data.manifest["settings"]["path"],
    )


# --------------------------------------------------------------------------- fits


def _save_fit(folder: Path, fit: MicrofacetFit) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    theta = {k: np.asarray(v).tolist() for k, v in fit.parameters().items()}
    theta.update(
        theta_mode=fit.params.theta_mode,
        phi_mode=fit.params.phi_mode,
        n_theta_cells=fit.grid.n_theta,
        n_phi_cells=fit.grid.n_phi,
        n_parameters=fit.n_parameters,
        rs_history=list(fit.rs_history),
    )
    save_json(folder, "parameters", theta)
    save_arrays(
        folder,
        observed=fit.observed,
        cell_measured=fit.cell_measured,
        objective=fit.objective,
        objective_outer=fit.objective_outer,
    )


def load_reconstruction(folder: str | Path) -> MicrofacetFit:
    """Rebuild a fitted BRDF from a folder holding ``parameters.json`` (e.g. the run's
    ``fit/`` artifacts); ``.evaluate(light, view)`` works at any pair of directions."""
    folder = Path(folder)
    theta = json.loads((folder / "parameters.json").read_text())
    grid = HemisphereGrid(int(theta["n_theta_cells"]), int(theta["n_phi_cells"]))

    def array(name, default):
        path = folder / f"{name}.npy"
        return np.load(path) if path.is_file() else default

    params = MixtureParams(
        u=np.asarray(theta["u"], float),
        v=np.asarray(theta["v"], float),
        tau=float(theta["tau"]),
        sigma=float(theta["sigma"]),
        gamma=float(theta["Gamma"]),
        lam=float(theta["Lambda"]),
        theta_mode=theta["theta_mode"],
        phi_mode=theta["phi_mode"],
    )
    return MicrofacetFit(
        params=params,
        rho_s=np.asarray(theta["rho_s"], float),
        rho_d=np.asarray(theta["rho_d"], float),
        rs=float(theta["Rs"]),
        grid=grid,
        observed=array("observed", np.zeros((grid.n_theta, grid.n_phi, 3))),
        cell_measured=array("cell_measured", np.zeros((grid.n_theta, grid.n_phi), bool)),
        objective=array("objective", np.zeros(0)),
        objective_outer=array("objective_outer", np.zeros(0, int)),
        rs_history=list(theta.get("rs_history", [])),
    )


def fit_stage(ctx: Context, data: Entry) -> Entry:
    """The method's fit (MAP with the Dirichlet prior on u)."""
    settings = em_settings(ctx.cfg)

    def compute(folder: Path) -> dict:
        start = time.perf_counter()
        fit = fit_microfacet_em(measured_brdf(data), settings)
        _save_fit(folder, fit)
        return {
            "n_parameters": fit.n_parameters,
            "rs": fit.rs,
            "seconds": time.perf_counter() - start,
            "em_iterations": int(fit.objective.size),
            "outer_iterations": int(fit.objective_outer.max(initial=-1)) + 1,
        }

    return ctx.run("brdf_fit", asdict(settings), {"brdf_data": data}, compute, version="1")


def baselines_stage(ctx: Context, data: Entry) -> Entry:
    """Baselines: the fit without prior (w_u = 0) and plain Ashikhmin-Shirley."""
    # w_u is 0 here whatever method.prior_strength says, so a sweep over w_u reuses this entry.
    em = replace(em_settings(ctx.cfg), prior_strength=0.0)
    base = plain_settings(ctx.cfg.method.baselines)
    settings = {"em": asdict(em), "seed": ctx.cfg.seed, **base}

    def compute(folder: Path) -> dict:
        brdf = measured_brdf(data)
        start = time.perf_counter()
        _save_fit(folder / "noprior", fit_without_prior(brdf, em))
        middle = time.perf_counter()
        as_fit = fit_ashikhmin_shirley(
            brdf,
            rng=np.random.default_rng(ctx.cfg.seed),
            max_samples=base["as_max_samples"],
            exponent_starts=tuple(tuple(float(x) for x in s) for s in base["as_exponent_starts"]),
        )
        params = {k: np.asarray(v).tolist() for k, v in as_fit.parameters().items()}
        save_json(folder, "ashikhmin_shirley", {**params, "cost": as_fit.cost})
        return {"seconds_noprior": middle - start, "seconds_as": time.perf_counter() - middle}

    return ctx.run("brdf_baselines", settings, {"brdf_data": data}, compute, version="1")


def _load_as(path: Path) -> AshikhminShirleyFit:
    p = json.loads(path.read_text())
    scalars = {name: float(p[name]) for name in ("nu", "nv", "phi0", "cost")}
    return AshikhminShirleyFit(
        rd=np.asarray(p["rd"], float), rs=np.asarray(p["rs"], float), **scalars
    )


# --------------------------------------------------------------------------- evaluation


def merl_lookup(brdf: brdf_io.MeasuredBRDF):
    """Nearest-cell lookup into MERL-ordered data, NaN where missing (raw data "with holes").

    Returns ``lookup(light (n, 2), view (n, 2)) -> (n, 3)``; the inverse of
    :func:`pipeline.data.brdf.half_diff_to_directions` followed by the MERL index formula.
    """
    table = np.where(brdf.measured[:, None], brdf.reflectance, np.nan)

    def lookup(light, view):
        k1, k2 = brdf_io.to_unit_vectors(light), brdf_io.to_unit_vectors(view)
        theta_h, phi_h, _ = brdf_io.half_vector_angles(light, view)
        c, s = np.cos(phi_h), np.sin(phi_h)  # rotate k1 by -phi_h about n, then -theta_h about b
        x, y = c * k1[:, 0] + s * k1[:, 1], -s * k1[:, 0] + c * k1[:, 1]
        ct, st = np.cos(theta_h), np.sin(theta_h)
        diff = np.stack([ct * x - st * k1[:, 2], y, st * x + ct * k1[:, 2]], -1)
        theta_d, phi_d = brdf_io.to_angles(diff).T
        eps = 1e-6  # grid angles must map back to their own cell despite rounding
        i_h = np.floor(np.sqrt(theta_h / (0.5 * np.pi)) * 90 + eps)
        i_d = np.floor(theta_d / (0.5 * np.pi) * 90 + eps)
        i_p = np.mod(np.floor(np.mod(phi_d, np.pi) / np.pi * 180 + eps), 180)  # reciprocity
        index = np.clip(i_p, 0, 179) + 180 * (np.clip(i_d, 0, 89) + 90 * np.clip(i_h, 0, 89))
        out = table[index.astype(np.int64)]
        out[(k1[:, 2] <= 0) | (k2[:, 2] <= 0)] = 0.0
        return out

    return lookup


def _figures(folder: Path, fig_cfg: dict, raw, models: dict) -> None:
    """Figs. 2-8: d and f, slices, spheres (``raw``: a lookup with NaN holes), objective."""
    # Imported here: matplotlib is not needed by the app's other methods.
    from matplotlib.figure import Figure

    from pipeline.brdf_map import figures as brdf_figures

    fit = models["reconstruction"]
    grid = fit.grid
    for name, model in (("distribution", fit), ("distribution_noprior", models["noprior"])):
        observed, fitted = model.observed, model.distribution_grid()
        brdf_figures.plot_distribution_heatmaps(
            grid.theta, grid.phi, observed, fitted, folder, model.cell_measured, name=name
        )
    phis, thetas = fig_cfg["slice_phi_deg"], fig_cfg["slice_theta_deg"]
    fitted = fit.distribution_grid()
    brdf_figures.plot_distribution_slices(
        grid.theta, grid.phi, fit.observed, fitted, folder, phis, thetas, fit.cell_measured
    )
    lights = [tuple(np.deg2rad(fig_cfg[k])) for k in ("near_light_deg", "far_light_deg")]
    size = int(fig_cfg["sphere_size"])
    renders = [brdf_figures.render_sphere(fit.evaluate, light, size) for light in lights]
    exposure = float(
        np.percentile(np.concatenate([img[inside].ravel() for img, inside in renders]), 99)
    )
    for name, model in {"raw": raw, **{k: m.evaluate for k, m in models.items()}}.items():
        brdf_figures.plot_sphere_pair(
            model, folder, f"spheres_{name}", *lights, size=size, exposure=max(exposure, 1e-12)
        )
    fig = Figure(figsize=(6, 3.5), constrained_layout=True)
    ax = fig.subplots()
    ax.plot(np.arange(fit.objective.size), fit.objective, lw=1)
    for start in np.flatnonzero(np.diff(fit.objective_outer)) + 0.5:
        ax.axvline(start, color="grey", ls=":", lw=0.8)  # d and Rs recomputed: J jumps
    ax.set_xlabel("EM iteration (dotted: next outer iteration)")
    ax.set_ylabel("objective J (log posterior)")
    save_figure(fig, folder / "objective.png", dpi=100)


def evaluate_stage(ctx: Context, data: Entry, fitted: Entry, baselines: Entry) -> Entry:
    """Metrics of the method and both baselines, the figures, the complete reconstruction."""
    fig_cfg = plain_settings(ctx.cfg.method.figures)

    def compute(folder: Path) -> dict:
        brdf = measured_brdf(data)
        fit = load_reconstruction(fitted.path)
        models = {
            "reconstruction": fit,
            "noprior": load_reconstruction(baselines.path / "noprior"),
            "as": _load_as(baselines.file("ashikhmin_shirley.json")),
        }
        above = brdf_io.above_horizon(brdf.light, brdf.view)
        has_truth = (data.path / "truth.npy").is_file()
        metrics = {"n_parameters": fit.n_parameters, "n_parameters_as": models["as"].n_parameters}
        if has_truth:
            truth = data.array("truth", mmap=False)
            missing = above & ~brdf.measured & data.array("truth_known", mmap=False)
            theta_h = brdf_io.half_vector_angles(brdf.light, brdf.view)[0]
            near = theta_h < np.deg2rad(NEAR_MIRROR_DEG)
            parts = {"near_mirror": missing & near, "off_mirror": missing & ~near}
            metrics.update({f"n_missing_{k}": int(v.sum()) for k, v in parts.items()})
        for suffix, key in (("", "reconstruction"), ("_noprior", "noprior"), ("_as", "as")):
            estimate = models[key].evaluate(brdf.light, brdf.view)
            metrics[f"rmse_measured{suffix}"] = rmse(
                estimate, brdf.reflectance, above & brdf.measured
            )
            if has_truth and missing.any():
                metrics[f"rmse_missing{suffix}"] = rmse(estimate, truth, missing)
                for part, mask in parts.items():
                    if mask.any():
                        metrics[f"rmse_missing_{part}{suffix}"] = rmse(estimate, truth, mask)
        generator = data.manifest["settings"]["synthetic"]
        if generator is not None:
            models["truth"] = SyntheticAnisotropicBRDF(
                **{k: tuple(v) if isinstance(v, list) else v for k, v in generator.items()}
            )
        light, view = brdf_io.utia_directions()
        brdf_io.write_utia_brdf(folder / "reconstruction_utia.bin", fit.evaluate(light, view))
        utia = data.manifest["settings"]["format"] == "utia"
        raw = brdf_io.utia_interpolator(brdf) if utia else merl_lookup(brdf)
        _figures(folder / "figures", fig_cfg, raw, models)
        save_json(folder, "metrics", metrics)
        return metrics

    inputs = {"brdf_data": data, "brdf_fit": fitted, "brdf_baselines": baselines}
    settings = {**fig_cfg, "near_mirror_deg": NEAR_MIRROR_DEG}
    # Version 2: the missing-region RMSE split near / off the mirror direction.
    return ctx.run("brdf_evaluate", settings, inputs, compute, version="2")


# --------------------------------------------------------------------------- the job


def run(ctx: Context) -> dict[str, float]:
    """The whole chain for ``method=brdf_map``; returns the metrics for MLflow."""
    data = data_stage(ctx)
    fitted = fit_stage(ctx, data)
    baselines = baselines_stage(ctx, data)
    evaluated = evaluate_stage(ctx, data, fitted, baselines)
    metrics = {k: float(v) for k, v in evaluated.json("metrics").items()}
    summary = fitted.manifest["summary"]
    metrics.update(
        rs=float(summary["rs"]),
        em_iterations=float(summary["em_iterations"]),
        outer_iterations=float(summary["outer_iterations"]),
        n_measured=float(data.manifest["summary"]["n_measured"]),
        n_missing=float(data.manifest["summary"]["n_missing"]),
    )
    # The objective J at every EM iteration as the metric ``objective`` (step = iteration).
    ctx.log.series("objective", list(enumerate(fitted.array("objective", mmap=False))))
    ctx.log.folder(evaluated.path / "figures", "figures")
    arrays = ("objective", "objective_outer", "observed", "cell_measured")
    for name in ("parameters.json", *(f"{array}.npy" for array in arrays)):
        ctx.log.file(fitted.file(name), "fit")
    ctx.log.file(evaluated.file("reconstruction_utia.bin"), "fit")
    ctx.log.file(baselines.file("ashikhmin_shirley.json"), "baselines")
    ctx.log.file(baselines.path / "noprior" / "parameters.json", "baselines/noprior")
    return metrics
