"""OpenVINO and NNCF imported with their usage telemetry declined for this process.

``import openvino`` (through ``openvino.tools.ovc``), ``import nncf`` and every
``nncf.quantize`` send usage events through ``openvino_telemetry`` unless a consent file
(``~/intel/openvino_telemetry``) says no or ``CI=true`` is set, so on a fresh machine they
do. Each event is sent from a helper thread through ``multiprocessing.Process`` with the
``fork`` start method: a fork of a process whose JAX, data-loader and evaluator threads are
running, which can deadlock the child and makes JAX warn; these machines also have no
network to send to. This project never wants that, so every OpenVINO and NNCF import of
``gac_jax`` and ``benchmarks`` goes through :func:`import_openvino` / :func:`import_nncf`:
the consent check is declined while they are imported (no event, no consent or client-id
file written) and the telemetry singleton's consent is cleared afterwards, which also
silences a module that the caller had imported earlier. Nothing is written to the user's
consent file: other programs keep their setting.
"""

from __future__ import annotations

import contextlib
import importlib
import threading

_lock = threading.Lock()


@contextlib.contextmanager
def _declined():
    try:
        from openvino_telemetry import Telemetry
        from openvino_telemetry.utils.opt_in_checker import ConsentCheckResult, OptInChecker
    except ImportError:  # no telemetry package: nothing is sent
        yield
        return
    with _lock:
        check = OptInChecker.check
        OptInChecker.check = lambda self, *args, **kwargs: ConsentCheckResult.DECLINED
        try:
            yield
        finally:
            OptInChecker.check = check
        # every send and session checks it; RuntimeError: never set up, so nothing is sent
        with contextlib.suppress(RuntimeError):
            Telemetry().consent = False


def _import(name: str):
    with _declined():
        return importlib.import_module(name)


def import_openvino():
    """The ``openvino`` module, imported without telemetry (see the module docstring)."""
    return _import("openvino")


def import_nncf():
    """The ``nncf`` module, imported without telemetry (see the module docstring)."""
    _import("openvino")  # nncf imports openvino: decline before either sends
    return _import("nncf")
