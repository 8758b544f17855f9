"""``python -m pipeline.bench key=value ...``: method A's training benchmark
(:mod:`pipeline.btf.fast.bench`; ``--help`` lists the settings)."""

from pipeline.btf.fast.bench_settings import parse_args


def main(argv: list[str] | None = None) -> dict:
    settings = parse_args(argv)  # before torch loads: a bad argument is answered at once
    from pipeline.btf.fast.bench import run

    return run(settings)


if __name__ == "__main__":
    main()
