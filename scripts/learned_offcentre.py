"""Open loop of an estimator on a camera whose principal point is off the sensor centre.

The renderers put the landing point at the sensor centre, so an off-centre principal point is
flown as the dataset build records it (:mod:`dvsland.data.crop`): the config's camera is the
larger centred sensor of :func:`dvsland.data.crop.recording_camera`, and :class:`OffCentre` hands
the wrapped estimator only the events of the off-centre window, in its own pixels, with its
principal point. Use it from ``dvsland evaluate`` (``--set`` the big camera, see ``--print-sets``)::

    python scripts/learned_offcentre.py --sensor davis346 --cx 140.5 --cy 150.5 --print-sets
    dvsland evaluate montecarlo_efference --threads 1 --sites A,B,C,D,E,F,G $(python scripts/learned_offcentre.py \\
        --sensor davis346 --cx 140.5 --cy 150.5 --print-sets) \\
        --estimators "davis346oc=scripts/learned_offcentre.py:OffCentre[sensor=davis346;cx=140.5;cy=150.5]"

Parameters (``estimator.params``): ``sensor`` (a camera.sensor preset), ``cx``, ``cy`` (the
principal point on it, px), ``inner`` (the wrapped estimator, default ``learned``), ``checkpoint``
(the learned checkpoint, default the shipped CNN).
"""

from __future__ import annotations

import argparse
from typing import Optional

import torch

from dvsland.estimators.base import DivergenceEstimator


def _window(sensor: str, cx: float, cy: float):
    from dvsland.config import CameraConfig
    from dvsland.data.crop import recording_camera

    cam = CameraConfig(sensor=sensor, principal_point_px=[float(cx), float(cy)])
    big, crop = recording_camera(cam)
    return cam, big, crop


class OffCentre(DivergenceEstimator):
    """``inner`` on the off-centre window of the (big, centred) camera the loop renders."""

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s: float = 0.1, sensor: str = "davis346",
                 cx: float = 140.5, cy: float = 150.5, inner: str = "learned", checkpoint: str = ""):
        super().__init__(batch_size, sensor_size, device, dt_s)
        from dvsland.estimators import get_estimator

        cam, big, crop = _window(sensor, cx, cy)
        if tuple(self.sensor_size) != (big.width_px, big.height_px):
            raise ValueError(f"sensor_size: the loop's camera is {tuple(self.sensor_size)}, the window needs the "
                             f"centred {big.width_px} x {big.height_px} (--print-sets)")
        self.crop = crop
        kw = {"checkpoint": checkpoint} if inner == "learned" else {}
        self.inner = get_estimator(inner, batch_size, (cam.width_px, cam.height_px), device, dt_s=dt_s,
                                   principal_point_px=[float(cx), float(cy)], **kw)

    def reset(self, mask: Optional[torch.Tensor] = None) -> None:
        self.inner.reset(mask)

    def update(self, events, t_us: int, truth=None) -> torch.Tensor:
        from dvsland.events import Events

        c = self.crop
        x, y = events.x - c.x0, events.y - c.y0
        k = (x >= 0) & (x < c.width) & (y >= 0) & (y < c.height)
        return self.inner.update(Events(b=events.b[k], x=x[k], y=y[k], t=events.t[k], p=events.p[k]), t_us, truth)

    @property
    def _d(self) -> torch.Tensor:
        return self.inner._d

    def confidence(self) -> torch.Tensor:
        return self.inner.confidence()

    def diagnostics(self):
        return self.inner.diagnostics()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensor", default="davis346")
    ap.add_argument("--cx", type=float, default=140.5)
    ap.add_argument("--cy", type=float, default=150.5)
    ap.add_argument("--print-sets", action="store_true", help="print the --set options of the big camera")
    a = ap.parse_args(argv)
    _, big, crop = _window(a.sensor, a.cx, a.cy)
    if a.print_sets:
        print(f"--set camera.width_px={big.width_px} --set camera.height_px={big.height_px} "
              f"--set camera.fov_deg={big.fov_deg!r}")
    else:
        print(big, crop)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
