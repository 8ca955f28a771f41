"""The filters (``moving_average``, ``efference``, ``efference_fit``) and the laws (``tau_p``, ``div_p``,
``div_gs``) as stages: params + State + pure step.

For each: the object API (``update``/``reset``, ``__call__``/``reset``) gives, bit for bit, the outputs
of the code before the stage contract (:data:`REFERENCE`: SHA-256 of whole trajectories, recorded on
:func:`_inputs`); the contract (``init_state``/``step_state``/``reset_where``) agrees with the object
API; the step is pure (the input state is left bit-identical; the same state stepped twice gives the
same outputs and next states); ``reset_where`` leaves the unmasked descents bit-identical; a
malformed State is a ValueError naming the stage and the field.
"""

from __future__ import annotations

import hashlib
import math

import pytest
import torch

import dvsland.control as C
from dvsland.pytree import has_stage_contract, tree_clone, tree_equal, tree_leaves

F64 = torch.float64
NAN = math.nan
B, K = 4, 24
Z0 = torch.tensor([4000.0, 10000.0, 4200.0, 3900.0], dtype=F64)
V0 = torch.tensor([-100.0, -200.0, -95.0, -110.0], dtype=F64)
#: step -> reset mask before it (the "masked" scenarios)
RESETS = {9: [True, False, False, True], 17: [False, True, False, False]}


def _inputs():
    """(K, B) inputs built from integer patterns (no random generator, exact on every machine):
    estimates around -0.025 1/s with NaN gaps and a few wrong-signed ones, confidences in [0, 1]
    (some 0), accelerations, active masks (``active``: some descents frozen at some steps;
    ``flying``: descent b flies steps 0 .. K - 4 b - 1, as in the loop), masses, altitudes."""
    k = torch.arange(K).unsqueeze(1)
    b = torch.arange(B).unsqueeze(0)
    d = -0.025 * (1 + ((k * 7 + b * 5) % 13 - 6).to(F64) / 60)
    d = torch.where((k * 3 + b) % 7 == 0, NAN, d)
    d_law = torch.where((k + 2 * b) % 11 == 5, 0.01, d)
    return {"d": d, "d_law": d_law, "conf": ((k * 5 + b * 3) % 10).to(F64) / 9,
            "accel": 1.0 + ((k * 11 + b) % 9 - 4).to(F64) / 8, "active": (k * 13 + b * 7) % 10 != 0,
            "flying": k < K - 4 * b, "mass": 1e4 - 3.0 * k.to(F64) - 7.0 * b.to(F64),
            "alt": (4000.0 - 170.0 * k.to(F64) - 11.0 * b.to(F64)).clamp_min(5.0)}


def _filters():
    """name -> (factory, scenario, use confidence)."""
    return {
        "ma": (lambda: C.MovingAverageFilter([1, 3, 5, 8]), "masked", False),
        "ekf": (lambda: C.EfferenceFilter(Z0, V0, 0.1), "masked", False),
        "ekf_robust": (lambda: C.EfferenceFilter(Z0, V0, 0.1, prior_scale=1.1, meas_noise="confidence", huber_k=1.5,
                                                 max_step_rel=0.02, cov_cap_rel=0.3, min_confidence=0.2,
                                                 prior_rel_sigma_v=0.2), "masked", True),
        "fit": (lambda: C.EfferenceFitFilter(Z0, V0, 0.1, meas_noise="confidence"), "flying", True),
        "fit_forget": (lambda: C.EfferenceFitFilter(Z0, V0, 0.1, forget_s=0.1, iterations=4, min_confidence=0.1),
                       "flying", True),
    }


def _laws():
    """name -> (factory, scenario, per-descent t_s tensor)."""
    kp = torch.tensor([5e6, 4e6, 3e6, 6e6], dtype=F64)
    tau0 = torch.tensor([40.0, 50.0, 42.0, 38.0], dtype=F64)
    return {
        "tau_p": (lambda: C.TauPController(kp / 1e3, tau0, 0.5, 1.62), "masked", False),
        "tau_p_hover": (lambda: C.TauPController(kp / 1e3, tau0, 0.5, 1.62, 1000.0, 3e4, "hover"), "all", True),
        "div_p": (lambda: C.DivPController(kp, tau0, 0.25, 1.623), "masked", True),
        "div_p_ff": (lambda: C.DivPController(kp, tau0, 0.25, 1.623, 0.0, 2e4, "hover", feedforward_mg=True),
                     "all", False),
        "div_gs": (lambda: C.DivGSController(tau0, 0.5, 1.62, 0.0, 1e5, lambda_per_s=0.7, v_min_mps=2.0),
                   "masked", True),
    }


def _filter_step_args(x, k, scenario, use_conf):
    mask = {"masked": x["active"][k], "flying": x["flying"][k]}.get(scenario)
    a = None if k == 0 else x["accel"][k - 1]
    return x["d"][k], mask, a, None if a is None else a + 1.62, x["conf"][k] if use_conf else None


def _law_step_args(x, k, scenario, tvec):
    t = k * 0.5
    t = torch.full((B,), t, dtype=F64) if tvec else t
    return t, x["d_law"][k], x["mass"][k], x["active"][k] if scenario == "masked" else None, x["alt"][k]


def fly_filter_object(name):
    """Outputs [(d_filtered, n_used, altitude_m or None)] of K steps through the object API."""
    make, scenario, use_conf = _filters()[name]
    f, x, out = make(), _inputs(), []
    for k in range(K):
        if scenario == "masked" and k in RESETS:
            f.reset(torch.tensor(RESETS[k]))
        d, mask, a, ta, conf = _filter_step_args(x, k, scenario, use_conf)
        d_f, n = f.update(d, mask=mask, accel_mps2=a, thrust_accel_mps2=ta, confidence=conf)
        out.append((d_f.clone(), n.clone(), f.altitude_m.clone() if hasattr(f, "altitude_m") else None))
    return out


def fly_law_object(name):
    """Outputs [(thrust_n, tau_hat_s, tau_target_s, held)] of K steps through the object API."""
    make, scenario, tvec = _laws()[name]
    c, x, out = make(), _inputs(), []
    for k in range(K):
        if scenario == "masked" and k in RESETS:
            c.reset(torch.tensor(RESETS[k]))
        t, d, m, act, alt = _law_step_args(x, k, scenario, tvec)
        kw = {"altitude_m": alt} if c.needs_altitude else {}
        o = c(t, d, m, act, **kw)
        out.append((o.thrust_n.clone(), o.tau_hat_s.clone(), torch.as_tensor(o.tau_target_s).clone(), o.held.clone()))
    return out


def digest(outs) -> str:
    """SHA-256 of a trajectory: every tensor as float64 with NaN and -0.0 made canonical."""
    h = hashlib.sha256()
    for row in outs:
        for t in row:
            if t is None:
                h.update(b"none")
                continue
            x = t.to(F64)
            h.update(torch.isnan(x).numpy().tobytes())
            h.update((torch.where(torch.isnan(x), 0.0, x) + 0.0).numpy().tobytes())
    return h.hexdigest()


#: SHA-256 of each trajectory (:func:`digest` of :func:`fly_filter_object` / :func:`fly_law_object`),
#: recorded with the filters and laws as they were before the stage contract (object API, attributes
#: as state). "fit" re-recorded when efference_fit's sums became per descent (batch first, so that a
#: compacted batch gives the same bits): its outputs moved by at most 1.4e-16 relative (one ulp)
REFERENCE = {
    "ekf": "75f553ff1940150fc5073e49301d962840c69eac4dd4df528e9a9264703f4a99",
    "ekf_robust": "a8d23c5255461069446fe021596b91698ce0ea32464b6ebf4972bba5f0485393",
    "fit": "27826d9574e4e2a79a6d34a700a7ba20c98f00761b13decc356dbd9822599df7",
    "fit_forget": "3854ed68aa8a95e995c7037955a23023d6ae0d4b9c53f4f916c3cb5ec0d59aaa",
    "ma": "4782590c3fca33ed9d930fd137833330e2e7aacc22e95ed48cc006a17a214a32",
    "div_gs": "232a09a2316de0381f21943e15c8d5cf73957086d39c450dfa401fcd4718950a",
    "div_p": "ae561c039b260bc49cacf1c04bdbbeeaeb19293f1820cd2243a405857e62c166",
    "div_p_ff": "7081cb740481440c9f769b2e2d0274a63584698ebce638e263d1635dd73e6526",
    "tau_p": "ee11155868f39f8ed8066cf45f308ef5ee602b798e412ac6c69bed4fc0771a3d",
    "tau_p_hover": "2a0fa63be17f29ccc77a314ae0f4a1258b49072a7938acc649124288617867c4",
}
#: the same trajectories recorded on other CPUs (by vendor id), where they round differently: "fit"'s
#: least-squares sums on an AMD EPYC (2026-11-27, from the code that recorded REFERENCE's "fit")
OTHER_CPUS = {"AuthenticAMD": {"fit": "e8bfa9fe2d386fc197f35b03e3f281d45a0a44f180e92b38c53bf8b3abe044f6"}}


def _recorded(name: str, recording_cpu: bool, vendor: str) -> tuple:
    """The digests ``name`` may have here: REFERENCE's, and this CPU's own recorded variant if any."""
    other = () if recording_cpu else tuple(v for v in [OTHER_CPUS.get(vendor, {}).get(name)] if v)
    return (REFERENCE[name],) + other


# ------------------------------------------------------------------ the previous outputs, bit for bit
@pytest.mark.parametrize("name", sorted(_filters()))
def test_filter_outputs_are_the_previous_ones(name, recording_cpu, cpu_vendor):
    assert digest(fly_filter_object(name)) in _recorded(name, recording_cpu, cpu_vendor)


@pytest.mark.parametrize("name", sorted(_laws()))
def test_law_outputs_are_the_previous_ones(name):
    assert digest(fly_law_object(name)) == REFERENCE[name]


# ------------------------------------------------------------------ the contract
def fly_filter_contract(name, steps=K):
    """(outputs as :func:`fly_filter_object`, the filter, the last state) through the contract."""
    make, scenario, use_conf = _filters()[name]
    f, x, out = make(), _inputs(), []
    st = f.init_state()
    for k in range(steps):
        if scenario == "masked" and k in RESETS:
            st = f.reset_where(st, torch.tensor(RESETS[k]))
        d, mask, a, ta, conf = _filter_step_args(x, k, scenario, use_conf)
        st, o = f.step_state(st, d, mask, a, ta, conf)
        assert isinstance(o, C.FilterOut) and o.d_filtered.dtype == F64 and o.n_used.dtype == torch.int64
        out.append((o.d_filtered, o.n_used, o.altitude_m))
    return out, f, st


def fly_law_contract(name, steps=K):
    """(outputs as :func:`fly_law_object`, the law, the last state) through the contract."""
    make, scenario, tvec = _laws()[name]
    c, x, out = make(), _inputs(), []
    st = c.init_state()
    for k in range(steps):
        if scenario == "masked" and k in RESETS:
            st = c.reset_where(st, torch.tensor(RESETS[k]))
        t, d, m, act, alt = _law_step_args(x, k, scenario, tvec)
        st, o = c.step_state(st, t, d, m, act, altitude_m=alt)
        assert isinstance(o, C.ControlOutput)
        out.append((o.thrust_n, o.tau_hat_s, torch.as_tensor(o.tau_target_s), o.held))
    return out, c, st


@pytest.mark.parametrize("name", sorted(_filters()))
def test_filter_contract_agrees_with_the_object_api(name, recording_cpu, cpu_vendor):
    out, f, _ = fly_filter_contract(name)
    assert digest(out) in _recorded(name, recording_cpu, cpu_vendor)
    assert digest(out) == digest(fly_filter_object(name))  # the two APIs agree on any CPU
    assert (out[-1][2] is None) == (not f.provides_altitude)


@pytest.mark.parametrize("name", sorted(_laws()))
def test_law_contract_agrees_with_the_object_api(name):
    assert digest(fly_law_contract(name)[0]) == REFERENCE[name]


def _mid_flight(kind, name):
    """(stage, a state after K // 2 steps, a step function of a state)."""
    x = _inputs()
    k = K // 2
    if kind == "filter":
        _, f, st = fly_filter_contract(name, k)
        use_conf = _filters()[name][2]
        d, mask, a, ta, conf = _filter_step_args(x, k, _filters()[name][1], use_conf)
        return f, st, lambda s: f.step_state(s, d, mask, a, ta, conf)
    _, c, st = fly_law_contract(name, k)
    t, d, m, act, alt = _law_step_args(x, k, _laws()[name][1], _laws()[name][2])
    return c, st, lambda s: c.step_state(s, t, d, m, act, altitude_m=alt)


STAGES = [("filter", n) for n in sorted(_filters())] + [("law", n) for n in sorted(_laws())]


@pytest.mark.parametrize("kind,name", STAGES)
def test_step_is_pure(kind, name):
    stage, st, step = _mid_flight(kind, name)
    before = tree_clone(st)
    s1, o1 = step(st)
    assert tree_equal(before, st)  # the input state is left as it was
    s2, o2 = step(st)
    assert tree_equal(s1, s2) and tree_equal(o1, o2)  # the same state, the same step
    assert getattr(stage, "state") is not st and not any(v is st for v in vars(stage).values())


@pytest.mark.parametrize("kind,name", STAGES)
def test_reset_where_keeps_the_other_descents(kind, name):
    stage, st, step = _mid_flight(kind, name)
    mask = torch.tensor([True, False, True, False])
    r = stage.reset_where(st, mask)
    fresh = stage.init_state()
    keep, redo = (~mask).nonzero().squeeze(1), mask.nonzero().squeeze(1)
    sel = lambda tree, i: {k: v[i] for k, v in tree_leaves(tree).items()}  # noqa: E731
    assert tree_equal(sel(r, keep), sel(st, keep))
    for k, v in sel(r, redo).items():
        if k.endswith("_packed"):
            assert torch.isnan(v).all()  # the restarted descents' history is blank
        else:
            assert tree_equal(v, sel(fresh, redo)[k]), k
    step(r)  # a restarted state steps


@pytest.mark.parametrize("kind,name", STAGES)
def test_a_bad_state_names_the_stage_and_the_field(kind, name):
    stage, st, step = _mid_flight(kind, name)
    field = st._fields[0]
    leaf = getattr(st, field)
    stage_name = type(stage).__name__
    with pytest.raises(ValueError, match=f"{stage_name}.*{field}.*dtype"):
        step(st._replace(**{field: leaf.to(torch.float32)}))
    with pytest.raises(ValueError, match=f"{stage_name}.*{field}.*shape"):
        step(st._replace(**{field: torch.cat([leaf, leaf[:1]])}))
    with pytest.raises(ValueError, match=f"{stage_name}.*state must be a {type(st).__name__}"):
        step(tuple(st))


class _NoSync:
    """Host syncs (``item``, ``tolist``, ``bool``, ``int``, ``float`` of a tensor) raise inside."""

    NAMES = ("item", "tolist", "__bool__", "__int__", "__float__")

    def __enter__(self):
        self.saved = {n: getattr(torch.Tensor, n) for n in self.NAMES}

        def refuse(*a, **k):
            raise AssertionError("host sync in a step")
        for n in self.NAMES:
            setattr(torch.Tensor, n, refuse)
        return self

    def __exit__(self, *exc):
        for n, f in self.saved.items():
            setattr(torch.Tensor, n, f)
        return False


@pytest.mark.parametrize("kind,name", STAGES)
def test_step_has_no_host_sync(kind, name):
    stage, st, step = _mid_flight(kind, name)
    with _NoSync():
        s1, _ = step(st)
        step(s1)


@pytest.mark.parametrize("name", sorted(_laws()))
def test_law_flight_time_per_descent(name):
    """``t_s`` is per descent: a (B,) tensor gives each descent what a float of its own time gives."""
    make, _, _ = _laws()[name]
    c = make()
    x = _inputs()
    st = c.init_state()
    t = torch.tensor([0.0, 3.5, 7.25, 11.0], dtype=F64)
    _, o = c.step_state(st, t, x["d_law"][3], x["mass"][3], None, altitude_m=x["alt"][3])
    for b in range(B):
        _, ob = c.step_state(st, float(t[b]), x["d_law"][3], x["mass"][3], None, altitude_m=x["alt"][3])
        assert all(torch.equal(u[b], v[b]) for u, v in zip(o, ob)
                   if u is not None and u[b].isnan().logical_not().all())  # residual: None but for a policy


def test_fit_history_stays_as_long_as_the_oldest_descent_in_flight():
    """Restarts one at a time (an environment's autoreset) blank the restarted descents' rows and drop
    the rows no descent uses; a restarted descent then flies like a fresh filter."""
    f = C.EfferenceFitFilter(Z0[:2], V0[:2], 0.1, meas_noise="confidence")
    x = _inputs()
    st = f.init_state()
    for k in range(K):
        if k in (8, 16):
            st = f.reset_where(st, torch.tensor([k == 8, k == 16]))
        a = None if k == 0 else x["accel"][k - 1][:2]
        st, o = f.step_state(st, x["d"][k][:2], None, a, None, x["conf"][k][:2])
        assert st.rows_packed.shape == (2, k + 1 - (8 if k >= 16 else 0), 5)
    g = C.EfferenceFitFilter(Z0[1:2], V0[1:2], 0.1, meas_noise="confidence")
    sg = g.init_state()
    for k in range(16, K):  # the same inputs (the restarted descent also dead-reckons its first step)
        a = x["accel"][k - 1][1:2]
        sg, og = g.step_state(sg, x["d"][k][1:2], None, a, None, x["conf"][k][1:2])
    torch.testing.assert_close(o.d_filtered[1:], og.d_filtered, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(o.altitude_m[1:], og.altitude_m, rtol=1e-12, atol=0.0)


def test_object_api_only_subclasses_run_as_object_stages():
    """A law (or filter) subclass with only the object API has no contract methods: the loop runs it
    through :class:`dvsland.pytree.ObjectStage`; the built-ins have the contract."""
    class Const(C.Controller):
        def __init__(self):
            self.batch_size, self.device, self.params = 2, "cpu", {"thrust_n": 1.0}  # its own attributes

        def reset(self, mask=None):
            pass

        def __call__(self, t_s, d_filtered, mass_kg, active=None):
            return C.ControlOutput(mass_kg, d_filtered, d_filtered, torch.isnan(d_filtered))

    class Echo(C.DivergenceFilter):
        def reset(self, mask=None):
            pass

        def update(self, d_hat, mask=None, **kw):
            return d_hat, torch.isfinite(d_hat).long()

    assert not has_stage_contract(Const()) and not has_stage_contract(Echo())
    for make, _, _ in list(_laws().values()) + list(_filters().values()):
        assert has_stage_contract(make())
    out = Const()(0.0, torch.tensor([NAN, -0.02], dtype=F64), torch.ones(2, dtype=F64))
    assert out.held.tolist() == [True, False]


def test_settings_read_as_attributes_and_the_object_api_holds_one_state():
    ekf = C.EfferenceFilter(Z0, V0, 0.1, prior_scale=1.2, gate_sigma=4.0)
    assert ekf.prior_scale == 1.2 and ekf.gate_sigma == 4.0 and ekf.prior_rel_sigma_v == ekf.prior_rel_sigma
    assert torch.equal(ekf.z, ekf.state.z) and ekf.n_rejected.dtype == torch.int64
    assert C.DivPController(torch.ones(2, dtype=F64), torch.ones(2, dtype=F64), 0.25, 1.62,
                            feedforward_mg=True).feedforward_mg
    law = C.DivGSController(torch.ones(2, dtype=F64), 0.5, 1.62, lambda_per_s=2.0)
    assert law.lambda_per_s == 2.0 and law.missing_policy == "hold"
    with pytest.raises(AttributeError, match="nope"):
        ekf.nope
    with pytest.raises(ValueError, match="mask"):
        law.reset(torch.tensor([1, 0]))


@pytest.mark.parametrize("name", ["ekf", "ekf_robust", "fit", "fit_forget"])
def test_nan_acceleration_is_no_efference_copy_for_that_descent(name):
    """A NaN acceleration (a descent's first step after a restart) steps that descent as ``accel_mps2=None``
    does, and the others as if it were not there: one step serves a batch with restarted descents."""
    _, f, st = fly_filter_contract(name, K // 2)
    x = _inputs()
    d, conf = x["d"][K // 2], x["conf"][K // 2]
    a = x["accel"][K // 2 - 1]
    nan_first = torch.where(torch.tensor([True, False, False, True]), NAN, a)
    s_mix, o_mix = f.step_state(st, d, None, nan_first, nan_first + 1.62, conf)
    s_none, o_none = f.step_state(st, d, None, None, None, conf)
    s_all, o_all = f.step_state(st, d, None, a, a + 1.62, conf)
    for b, ref in ((0, o_none), (1, o_all), (2, o_all), (3, o_none)):
        assert all(u is v is None or tree_equal(u[b], v[b]) for u, v in zip(o_mix, ref)), b  # None: no doubt
        assert all(tree_equal(u[b], v[b]) for u, v in zip(s_mix, s_none if ref is o_none else s_all)), b
