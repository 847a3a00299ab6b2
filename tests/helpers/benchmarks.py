"""A script of benchmarks/ loaded as a module, for the tests that run it or read its targets."""

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def load_benchmark(script: str) -> ModuleType:
    """benchmarks/<script>.py as the module ``cubetrack_benchmark_<script>``, loaded once and registered in
    sys.modules so that worker processes (accuracy.py --jobs) can unpickle its functions."""
    name = f"cubetrack_benchmark_{script}"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{script}.py")
        assert spec is not None and spec.loader is not None, script
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]
