"""What the compiled train step needs in device memory, what the device has, and a device
out-of-memory error as one line.

:func:`compile_step` compiles the jitted step ahead of time (``.lower(...).compile()``: the
loop then calls the compiled executable, so nothing compiles twice), announcing the compile
and its seconds. :func:`memory_line` reads XLA's ``compiled.memory_analysis()`` (per device:
the program of one SPMD partition) and the device's ``memory_stats()`` (GPU/TPU; the CPU
backend reports none, so the host's RAM is shown). A ``RESOURCE_EXHAUSTED`` error of XLA
becomes :class:`DeviceMemoryError`: one line naming ``data.batch_size`` and the need; the XLA
text goes to the run's details file (:mod:`gac_jax.training.run_log`).
"""

from __future__ import annotations

import dataclasses
import os
import time

import jax

from gac_jax.training import run_log

GIB = 1024**3


class DeviceMemoryError(RuntimeError):
    """The train step ran out of device memory; the message says what to change."""


@dataclasses.dataclass(frozen=True)
class StepMemory:
    """Bytes one device needs for the compiled step (XLA's buffer assignment)."""

    arguments: int
    outputs: int
    temporaries: int
    aliased: int  # outputs written into donated argument buffers (counted once)
    code: int

    @property
    def total(self) -> int:
        return self.arguments + self.outputs - self.aliased + self.temporaries + self.code

    @classmethod
    def of(cls, compiled) -> StepMemory | None:
        """From ``compiled.memory_analysis()``; None where the backend does not tell."""
        try:
            m = compiled.memory_analysis()
        except Exception:  # noqa: BLE001 - optional on some backends
            return None
        if m is None:
            return None
        return cls(
            arguments=int(m.argument_size_in_bytes),
            outputs=int(m.output_size_in_bytes),
            temporaries=int(m.temp_size_in_bytes),
            aliased=int(m.alias_size_in_bytes),
            code=int(m.generated_code_size_in_bytes),
        )

    def describe(self) -> str:
        unit, size = ("GiB", GIB) if self.total >= GIB // 2 else ("MiB", 1024**2)
        return (
            f"{self.total / size:.2f} {unit} (arguments {self.arguments / size:.2f}, outputs "
            f"{self.outputs / size:.2f}, temporaries {self.temporaries / size:.2f}, donated "
            f"-{self.aliased / size:.2f})"
        )

    def as_record(self) -> dict[str, int]:
        return dict(dataclasses.asdict(self), total=self.total)


def device_memory(device=None) -> str:
    """What ``device`` has: its allocator limit and use (GPU/TPU) or the host RAM (CPU)."""
    device = device or jax.local_devices()[0]
    stats = None
    try:
        stats = device.memory_stats()
    except Exception:  # noqa: BLE001 - not implemented on some backends
        stats = None
    if stats and "bytes_limit" in stats:
        used = stats.get("bytes_in_use", 0)
        return (
            f"{device.device_kind} has {stats['bytes_limit'] / GIB:.2f} GiB for JAX "
            f"({used / GIB:.2f} GiB in use)"
        )
    total, available = host_ram()
    if total is None:
        return f"{device.device_kind}: JAX does not report its memory"
    return f"{device.platform} device: host RAM {total / GIB:.2f} GiB" + (
        f" ({available / GIB:.2f} GiB available)" if available is not None else ""
    )


def host_ram() -> tuple[int | None, int | None]:
    """(total, available) bytes of host RAM (None where unknown)."""
    available = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = None
    return total, available


def memory_line(memory: StepMemory | None, device=None) -> str:
    need = memory.describe() if memory is not None else "unknown (XLA does not say)"
    return f"train step memory per device: {need}; {device_memory(device)}"


def compile_step(jitted, *args, announce: bool = True, what: str = "the train step"):
    """``(compiled, seconds)``: ``jitted.lower(*args).compile()``, announced when ``announce``
    ("compiling the train step ..." before, the seconds after)."""
    if announce:
        print(f"compiling {what} ...", end="", flush=True)
    t0 = time.perf_counter()
    try:
        compiled = jitted.lower(*args).compile()
    except BaseException:
        if announce:
            print(" failed", flush=True)
        raise
    seconds = time.perf_counter() - t0
    if announce:
        print(f" {seconds:.1f} s", flush=True)
    return compiled, seconds


def is_out_of_memory(error: BaseException) -> bool:
    """True for XLA's device out-of-memory error (``RESOURCE_EXHAUSTED``)."""
    return isinstance(error, jax.errors.JaxRuntimeError) and "RESOURCE_EXHAUSTED" in str(error)


def raise_if_out_of_memory(
    error: BaseException, batch_size: int, memory: StepMemory | None, device=None
) -> None:
    """Re-raises XLA's out-of-memory ``error`` as one :class:`DeviceMemoryError` line
    (the XLA text goes to the run's details file); any other error passes through."""
    if not is_out_of_memory(error):
        return
    run_log.record_exception(error)
    first = str(error).strip().splitlines()[0] if str(error).strip() else "RESOURCE_EXHAUSTED"
    if len(first) > 160:
        first = first[:157] + "..."
    need = f"needs {memory.describe()} per device" if memory is not None else "does not fit"
    details = run_log.active_path()
    raise DeviceMemoryError(
        f"out of device memory: the train step at data.batch_size={batch_size} {need}, "
        f"{device_memory(device)}; lower data.batch_size (or use train.compute_dtype=bfloat16)"
        f" [XLA: {first}]" + (f" (details in {details})" if details else "")
    ) from error
