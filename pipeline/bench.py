"""``python -m pipeline.bench``: method A's training benchmark (:mod:`pipeline.btf.fast.bench`)."""

from pipeline.btf.fast.bench import main

if __name__ == "__main__":
    main()
