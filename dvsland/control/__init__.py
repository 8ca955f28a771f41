"""Control: the TTC target, the divergence filters and the thrust laws, selected by name.

Laws (``controller.name``): ``tau_p`` (paper Eq. 2 in tau-space), ``div_p`` (the paper's released
implementation: proportional in divergence space), ``div_gs`` (gain scheduled on the
efference-copy altitude, soft-landing profile), ``policy`` (a small network trained through the loop); more with :func:`register_controller` or the
``dvsland.controllers`` entry-point group. Filters (``controller.filter``): ``moving_average``
(the paper's), ``efference`` (EKF fusing D_hat with the known thrust) and ``efference_fit`` (robust
batch fit of the initial-state error to every D_hat so far).

Every filter and law is a stage under the contract of :mod:`dvsland.pytree`: frozen params, a
State NamedTuple of (B, ...) tensors and a pure module-level step, behind ``init_state()``,
``step_state(state, ...)`` and ``reset_where(state, mask)``; filters return :class:`FilterOut`,
laws :class:`ControlOutput`. The object API (a filter's ``update``/``reset``, a law's
``__call__``/``reset``) is a thin wrapper holding one state in ``self.state``.

Public names: :func:`tau_target`, :func:`initial_ttc`, :func:`nan_moving_average`, :class:`FilterOut`,
:class:`DivergenceFilter`, the states, params and pure steps of every filter and law,
:class:`MovingAverageFilter`, :class:`EfferenceFilter`, :class:`EfferenceFitFilter`, :class:`Controller`, :class:`ControlOutput`,
:class:`DescentParams`, :class:`TauPController`, :class:`DivPController`, :class:`DivGSController`,
:func:`register_controller`, :func:`available_controllers`, :func:`get_controller`,
:func:`make_controller`, :func:`make_filter`, :func:`descent_params`, and the gain maths
:func:`tau_loop_gain`, :func:`div_loop_gain`, :func:`critical_step_gain`, :func:`gain_limit_altitude_m`.
"""

from .base import ControlOutput, Controller, HoldLastState, LawParams
from .efference import EfferenceFilter, EfferenceParams, EfferenceState, confidence_rel_sigma, efference_step
from .efference_fit import EfferenceFitFilter, EfferenceFitParams, EfferenceFitState, efference_fit_step
from .filter import (DivergenceFilter, FilterOut, MovingAverageFilter, MovingAverageParams, MovingAverageState,
                     moving_average_step, nan_moving_average)
from .gain import critical_step_gain, div_loop_gain, gain_limit_altitude_m, tau_loop_gain
from .params import DescentParams
from .registry import (available_controllers, controller_class, get_controller, refresh_entry_points,
                       register_controller)
from .target import initial_ttc, tau_target
from .tau_p import TauPController, tau_p_step
from .div_p import DivPController, div_p_step  # noqa: E402 - registers 'div_p'
from .div_gs import DivGSController, div_gs_step, divergence_target  # noqa: E402 - registers 'div_gs'
from .policy import PolicyController, PolicyNet, load_policy, policy_law_step  # noqa: E402 - registers 'policy'
from .factory import FILTER_NAMES, descent_params, filter_name, make_controller, make_filter  # noqa: E402

__all__ = ["tau_target", "initial_ttc", "nan_moving_average", "FilterOut", "DivergenceFilter", "MovingAverageFilter",
           "MovingAverageParams", "MovingAverageState", "moving_average_step", "EfferenceFilter", "EfferenceParams",
           "EfferenceState", "efference_step", "EfferenceFitFilter", "EfferenceFitParams", "EfferenceFitState",
           "efference_fit_step", "confidence_rel_sigma", "Controller", "ControlOutput", "LawParams", "HoldLastState",
           "tau_p_step", "div_p_step", "div_gs_step", "DescentParams", "TauPController", "DivPController", "DivGSController",
           "divergence_target", "PolicyController", "PolicyNet", "load_policy", "policy_law_step", "register_controller", "available_controllers", "controller_class", "get_controller",
           "refresh_entry_points", "make_controller", "make_filter", "descent_params", "filter_name",
           "FILTER_NAMES", "tau_loop_gain", "div_loop_gain", "critical_step_gain", "gain_limit_altitude_m"]
