"""Print the newest sweep of a store: its parent run and each child's status and RMSE.

    python scripts/sweep_status.py --uri sqlite:///runs/mlflow.db [--experiment btf]

Exits 1 unless the parent and at least one child exist and all of them are FINISHED, so
the scale-out scripts (``scripts/slurm_sweep.sh``, ``scripts/tracking_server_sweep.sh``)
can end with it as their check.
"""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--uri", required=True, help="tracking URI (sqlite:///… or http://…)")
    parser.add_argument("--experiment", default="btf")
    args = parser.parse_args(argv)

    from mlflow.tracking import MlflowClient

    client = MlflowClient(args.uri)
    experiment = client.get_experiment_by_name(args.experiment)
    if experiment is None:
        print(f"no experiment {args.experiment!r} in {args.uri}", file=sys.stderr)
        return 1
    parents = client.search_runs(
        [experiment.experiment_id],
        "tags.`sweep.dir` != ''",
        order_by=["attributes.start_time DESC"],
        max_results=1,
    )
    if not parents:
        print(f"no sweep in experiment {args.experiment!r} of {args.uri}", file=sys.stderr)
        return 1
    parent = parents[0]
    children = client.search_runs(
        [experiment.experiment_id], f"tags.mlflow.parentRunId = '{parent.info.run_id}'"
    )
    print(f"{args.uri}, experiment {args.experiment}")
    print(f"parent {parent.info.run_name} ({parent.info.run_id}): {parent.info.status}")
    for child in sorted(children, key=lambda run: run.info.run_name or ""):
        rmse = child.data.metrics.get("rmse")
        shown = f"rmse {rmse:.4f}" if rmse is not None else "no rmse"
        print(f"  child {child.info.run_name}: {child.info.status}, {shown}")
    finished = sum(child.info.status == "FINISHED" for child in children)
    print(f"{finished} of {len(children)} children FINISHED")
    ok = children and finished == len(children) and parent.info.status == "FINISHED"
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
