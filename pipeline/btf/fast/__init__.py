"""The fast training path of method A: the decoder step written out by hand (``fused``),
its C++ kernels (``kernels``), opt-in machine tuning (``tuning``) and the benchmark that
measures them (``python -m benchmarks.train``)."""
