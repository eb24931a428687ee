"""Shared test settings."""

import contextlib
import importlib.util
import io
import os
import runpy
import subprocess
import sys
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
import torch

#: The repository's root.
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    """Small networks on a small machine: one thread is fastest and avoids oversubscription."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def run_benchmark() -> Callable[..., subprocess.CompletedProcess]:
    """Run a script of ``benchmarks/`` as a user does, in the repository's root with this checkout's package.

    The returned function takes the script's name, its arguments and ``check`` (raise if the
    script fails, default False), and returns the finished process with its output as text.
    """
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}

    def run(script: str, *arguments: str, check: bool = False) -> subprocess.CompletedProcess:
        command = [sys.executable, str(ROOT / "benchmarks" / script), *arguments]
        return subprocess.run(command, check=check, capture_output=True, text=True, cwd=ROOT, env=env)

    return run


@pytest.fixture(scope="module")
def benchmark_module() -> Callable[[str], ModuleType]:
    """Import a script of ``benchmarks/`` as a module, to test its functions.

    The returned function takes the script's file name (e.g. ``"predictive_headroom.py"``) and
    returns the module; its ``main`` does not run.
    """

    def load(script: str) -> ModuleType:
        spec = importlib.util.spec_from_file_location(Path(script).stem, ROOT / "benchmarks" / script)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture
def run_benchmark_here(monkeypatch: pytest.MonkeyPatch) -> Callable[..., subprocess.CompletedProcess]:
    """Run a script of ``benchmarks/`` in this process, as ``python benchmarks/<script>`` would run it.

    For light work: a report, or bad input that the script refuses before any work. It spares the
    imports of a fresh interpreter; a script that trains or starts processes runs with
    :func:`run_benchmark`. The returned function takes what that of :func:`run_benchmark` takes
    and returns the exit code and the output as a finished process (1, with the traceback on
    stderr, for an exception).
    """
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))  # as for a script: its folder first on the path

    def run(script: str, *arguments: str, check: bool = False) -> subprocess.CompletedProcess:
        path = ROOT / "benchmarks" / script
        monkeypatch.setattr(sys, "argv", [str(path), *arguments])
        stdout, stderr, code = io.StringIO(), io.StringIO(), 0
        threads = torch.get_num_threads()
        with contextlib.chdir(ROOT), warnings.catch_warnings():  # the filters a script sets end with it
            with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
                try:
                    runpy.run_path(str(path), run_name="__main__")
                except SystemExit as end:
                    code = end.code or 0 if end.code is None or isinstance(end.code, int) else 1
                    if code == 1 and not isinstance(end.code, int):  # a message: as the interpreter prints it
                        print(end.code, file=sys.stderr)
                except Exception:
                    traceback.print_exc()
                    code = 1
                finally:
                    torch.set_num_threads(threads)
        done = subprocess.CompletedProcess(sys.argv, code, stdout.getvalue(), stderr.getvalue())
        if check:
            done.check_returncode()
        return done

    return run
