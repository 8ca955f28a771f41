"""``dvsland build-native``: compile the optional C++ kernels (the emulator's and ``cmax``'s) once
per machine and Python environment; afterwards every process uses them (mode auto), with events
and estimates identical to the torch path."""

from __future__ import annotations


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "build-native", help="compile the optional C++ kernels of the emulator and cmax (once, about a minute)",
        description="Compile the emulator's and cmax's C++ kernels with torch's cpp_extension (needs a C++ "
                    "compiler) into torch's extension cache (TORCH_EXTENSIONS_DIR if set). Every later process "
                    "uses them where built (DVSLAND_NATIVE_SORT / DVSLAND_NATIVE_CMAX = auto, the default): "
                    "the same events and estimates, cmax 2.5-3.5x and the emulator about 2x cheaper "
                    "(docs/howto/devices.md). Nothing compiles without this command.")
    p.set_defaults(func=run_build_native)


def run_build_native(args) -> int:
    from dvsland.estimators import native_cmax
    from dvsland.events import native
    from dvsland.native_build import timed_build

    rc = timed_build("the emulator kernels (dvsland.events.native)", native)
    return max(rc, timed_build("the cmax kernel (dvsland.estimators.native_cmax)", native_cmax))
