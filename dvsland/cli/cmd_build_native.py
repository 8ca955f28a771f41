"""``dvsland build-native``: compile the C++ kernels (the terrain's, the renderer's, the emulator's, ``cmax``'s,
``dpr``'s) ahead of use.
Every process builds them on first use anyway where a C++ compiler is found (a second or two,
once per machine); this command does it now and reports the time and the folder, or the error."""

from __future__ import annotations


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "build-native", help="compile the C++ kernels of the terrain, the renderer, the emulator, cmax and dpr now (a "
                             "second or two each; otherwise done on first use)",
        description="Compile the terrain's, the fast renderer's, the emulator's, cmax's, dpr's and the efference_fit "
                    "filter's C++ kernels (needs "
                    "a C++ compiler: $CXX, c++, g++ or clang++) into the kernel cache (~/.cache/torch_extensions/dvsland, or $TORCH_EXTENSIONS_DIR). "
                    "Every process builds them on first use anyway where a compiler is found "
                    "(DVSLAND_NATIVE_TERRAIN / DVSLAND_NATIVE_RENDER / DVSLAND_NATIVE_SORT / DVSLAND_NATIVE_CMAX / "
                    "DVSLAND_NATIVE_DPR / DVSLAND_NATIVE_FIT = auto, the default) and uses them: the same terrain, "
                    "frames, events, estimates and fits as the torch path, cmax 2.5-3.5x, the emulator and the "
                    "renderer's sampling about 2x "
                    "cheaper (docs/howto/devices.md). This command reports the build's time and folder, or its error.")
    p.set_defaults(func=run_build_native)


def run_build_native(args) -> int:
    from dvsland.control import native_fit
    from dvsland.estimators import native_cmax, native_dpr
    from dvsland.events import native
    from dvsland.native_build import timed_build
    from dvsland.render import native_render
    from dvsland.terrain import native_noise

    rc = timed_build("the terrain noise kernel", native_noise.LIBRARY)
    rc = max(rc, timed_build("the renderer kernels", native_render.LIBRARY))
    rc = max(rc, timed_build("the emulator kernels", native.LIBRARY))
    rc = max(rc, timed_build("the cmax kernel", native_cmax.LIBRARY))
    rc = max(rc, timed_build("the dpr kernels (mean-shift, peak scores)", native_dpr.LIBRARY))
    return max(rc, timed_build("the efference_fit filter's round terms", native_fit.LIBRARY))
