"""Fig. 8's cloth rendered by Mitsuba 3 and by the project's tracer for compressed models of
the built-in material, each scored against the analytic truth (rendered by the tracer)
and against the other renderer: RMSE of linear radiance and LDR-FLIP of the frame as
displayed, seconds per frame of each renderer on this machine. One JSON line a model, and
a figure (truth, then each model by Mitsuba):

    python scripts/mitsuba_compare.py --material corduroy --figure docs/figures/x.png \\
        neural_btf=runs/artifacts/<run>/artifacts/compressed/btf.safetensors pca=...
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", help="name=path of a btf.safetensors file")
    parser.add_argument("--material", default="corduroy")
    parser.add_argument("--texture", type=int, default=128, help="the built-in texture's side")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--spp", type=int, default=128)
    parser.add_argument("--figure", default=None)
    args = parser.parse_args()

    import mitsuba as mi

    from pipeline.btf.render.mitsuba_scene import (
        fig8_scene,
        material_from_file,
        mitsuba_dict,
        render,
        scene_description,
    )
    from pipeline.btf.render.surfaces import AnalyticMaterial
    from pipeline.btf.synthetic import SyntheticBTF
    from pipeline.core.image_metrics import flip
    from pipeline.data.images import gamma_encode
    from pipeline.render import mitsuba_bsdf
    from pipeline.render.engine import render_with_stats

    mitsuba_bsdf.register(None)
    scene = fig8_scene(args.size, args.size, "sheet", floor=False)

    def shown(image):
        return np.clip(gamma_encode(image), 0, 1).astype(np.float64)

    def rmse(a, b):
        return float(np.sqrt(np.mean(np.square(a - b, dtype=np.float64))))

    materials = {
        name: material_from_file(path) for name, path in (m.split("=", 1) for m in args.models)
    }
    crop = next(iter(materials.values())).crop_size
    truth_material = AnalyticMaterial(
        SyntheticBTF(size=args.texture, material=args.material), (0, 0), crop
    )
    truth, stats = render_with_stats(scene, truth_material, args.spp, seed=0)
    print(
        json.dumps(
            {
                "truth_seconds": round(stats.seconds, 1),
                "variant": mi.variant(),
                "size": args.size,
                "spp": args.spp,
            }
        ),
        flush=True,
    )
    panels = [("truth (tracer)", truth)]
    for name, material in materials.items():
        tracer, stats = render_with_stats(scene, material, args.spp, seed=0)
        started = time.perf_counter()
        with tempfile.TemporaryDirectory() as folder:  # the scene's mesh files
            description = scene_description(
                scene, folder, mitsuba_bsdf.material_bsdf(material), args.spp
            )
            loaded = mi.load_dict(mitsuba_dict(description))
        mitsuba = render(loaded, args.spp, seed=0)
        seconds = time.perf_counter() - started
        print(
            json.dumps(
                {
                    "model": name,
                    "mitsuba_seconds": round(seconds, 1),
                    "tracer_seconds": round(stats.seconds, 1),
                    "rmse_mitsuba_vs_tracer": rmse(mitsuba, tracer),
                    "flip_mitsuba_vs_tracer": flip(shown(tracer), shown(mitsuba)),
                    "rmse_mitsuba_vs_truth": rmse(mitsuba, truth),
                    "flip_mitsuba_vs_truth": flip(shown(truth), shown(mitsuba)),
                    "rmse_tracer_vs_truth": rmse(tracer, truth),
                    "flip_tracer_vs_truth": flip(shown(truth), shown(tracer)),
                }
            ),
            flush=True,
        )
        panels.append((f"{name} (Mitsuba)", mitsuba))
    if args.figure:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(3 * len(panels), 3.2))
        for ax, (title, image) in zip(fig.subplots(1, len(panels)), panels, strict=True):
            ax.imshow(shown(image))
            ax.set_title(title, fontsize=9)
            ax.axis("off")
        fig.tight_layout()
        fig.savefig(args.figure, dpi=100)


if __name__ == "__main__":
    main()
