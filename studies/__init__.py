"""Studies that use the library and are never used by it: paper reproductions, documentation
figures, real-sky studies and benchmarks (``rollingstar reproduce``, ``figures``, ``bench``)."""
