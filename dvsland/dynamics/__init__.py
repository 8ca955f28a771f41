"""Lander dynamics (paper Eq. 1) and the closed-form ideal descent.

Public names: :class:`LanderParams`, :class:`LanderDynamics`, :func:`step_exact`,
:func:`step_euler`, :func:`step_substeps`, ``INTEGRATORS``, :func:`closed_form_state`,
:func:`closed_form_time_to_altitude`, :func:`closed_form_thrust`, :func:`closed_form_descent`, :func:`loop_gain`.
"""

from .closed_form import (closed_form_descent, closed_form_state, closed_form_thrust, closed_form_time_to_altitude,
                          loop_gain)
from .lander import INTEGRATORS, LanderDynamics, LanderParams, step_euler, step_exact, step_substeps

__all__ = ["LanderParams", "LanderDynamics", "INTEGRATORS", "step_exact", "step_euler", "step_substeps",
           "closed_form_state", "closed_form_time_to_altitude", "closed_form_thrust", "closed_form_descent", "loop_gain"]
