"""``python -m benchmarks.train key=value ...``: method A's training benchmark
(:mod:`benchmarks.train_figures`; ``--help`` lists the settings)."""

from benchmarks.train_settings import parse_args


def main(argv: list[str] | None = None) -> dict:
    """Measure, print and record the figures; returns them."""
    settings = parse_args(argv)  # before torch loads: a bad argument is answered at once
    from benchmarks.train_figures import run

    return run(settings)


if __name__ == "__main__":
    main()
