"""dvsland.envs: the gymnasium vector env over the batched loop flies the descents of
dvsland.simulate when fed the shipped controller's commands, follows gymnasium's API (check_env,
NEXT_STEP autoreset, seeding) and refuses bad observation names and actions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

gym = pytest.importorskip("gymnasium")

import dvsland  # noqa: E402
from dvsland.envs import ENV_ID, LandingEnv, LandingVectorEnv  # noqa: E402
from dvsland.sim import init_state, loop_step  # noqa: E402
from dvsland.stages import build_stages  # noqa: E402

QUIET = ["logging.tensorboard=false", "logging.figures=false", "render.threads=1"]


pytestmark = pytest.mark.usefixtures("one_thread")  # the shared fixture of conftest.py


def fly_episode(env, policy=None, max_steps=100_000):
    """Run one batch episode; ``policy(obs, info)`` -> actions (default: the controller's commands).
    Returns (per-element outcome names, t_end_s, z_end_m, rewards summed) and the step count."""
    obs, info = env.reset()
    B = env.num_envs
    outcome, t_end, z_end = [None] * B, np.full(B, np.nan), np.full(B, np.nan)
    ret = np.zeros(B)
    for n in range(max_steps):
        act = info["controller_thrust_n"] if policy is None else policy(obs, info)
        obs, rew, term, trunc, info = env.step(np.nan_to_num(act))
        ret += np.where([o is None for o in outcome], rew, 0.0)  # the first episode of each env only
        for b in np.flatnonzero(term | trunc):  # (an env restarts after its end)
            if outcome[b] is None:
                outcome[b], t_end[b], z_end[b] = info["outcome"][b], info["t_s"][b], info["z_m"][b]
        if all(o is not None for o in outcome):
            return (outcome, t_end, z_end, ret), n + 1
    raise AssertionError("episode did not end")


@pytest.mark.parametrize("preset,overrides", [("paper", []), pytest.param(  # 13 s: every dispersion on
    "montecarlo_efference", ["simulation.n_seeds=2"], marks=pytest.mark.slow)])
def test_controller_commands_reproduce_simulate(tmp_path, preset, overrides):
    """Raw thrust actions = info['controller_thrust_n']: same outcome, t_end and final altitude (bit
    for bit) as dvsland.simulate, oracle estimator, sites D and H."""
    env = LandingVectorEnv(config=preset, overrides=overrides + QUIET, sites="D,H", estimator="oracle",
                           observation="oracle", action="thrust_n", start_dispersion=0.0)
    (outcome, t_end, z_end, _), _ = fly_episode(env)
    res = dvsland.simulate(preset, estimator="oracle", sites="D,H", quiet=True, out=tmp_path / "run",
                           overrides=overrides + QUIET)
    assert [r["run"] for r in res.runs] == list(env.layout.run_label)
    assert outcome == [r["outcome"] for r in res.runs]
    np.testing.assert_allclose(t_end, [r["t_end_s"] for r in res.runs], rtol=0, atol=1e-9)
    assert z_end.tolist() == [r["z_end_m"] for r in res.runs]
    assert "success" in outcome


def test_agent_thrust_flies_like_loop_step_with_that_thrust():
    """An action other than the controller's command flies exactly loop_step(thrust=u)."""
    env = LandingVectorEnv(config="paper", overrides=QUIET, sites="D,E", estimator="oracle",
                           observation="oracle", action="thrust_n", start_dispersion=0.0)
    stages = build_stages(env.stages.cfg, env.layout)  # a second, independent loop of the same batch
    state = init_state(stages)
    mg = stages.settings.mass_kg * stages.settings.g_mps2
    _, info = env.reset()
    rng = np.random.default_rng(0)
    for k in range(60):
        u = np.where(rng.random(env.num_envs) < 0.5, info["controller_thrust_n"], mg * rng.uniform(0.5, 1.5, 4))
        _, _, _, _, info = env.step(u)
        state, _ = loop_step(stages, state, thrust=torch.as_tensor(u))
        np.testing.assert_array_equal(info["z_m"], state.z_m.numpy())
        np.testing.assert_array_equal(info["v_mps"], state.v_mps.numpy())


def test_normalised_thrust_maps_onto_the_engine_range():
    env = LandingVectorEnv(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle",
                           num_envs=1)
    spec = env.action_spec
    mg3 = 3 * 10000.0 * 1.623  # paper: no thrust_max_n -> 3 m0 g
    assert (spec.low, spec.high, spec.thrust_low_n) == (-1.0, 1.0, 0.0)
    assert spec.thrust_high_n == pytest.approx(mg3)
    env.reset()
    for a, u in ((-1.0, 0.0), (1.0, mg3), (0.0, mg3 / 2)):
        env.reset()
        _, _, _, _, info = env.step(np.array([a]))
        assert info["thrust_n"][0] == pytest.approx(u)
    mc = LandingVectorEnv(config="montecarlo_efference", sites="D", estimator="oracle", observation="oracle",
                          overrides=QUIET)
    assert mc.action_spec.thrust_high_n == 100000.0


@pytest.mark.filterwarnings("ignore:.*Box observation space (minimum|maximum) value")  # documented: unbounded
def test_check_env_single_descent():
    from gymnasium.utils.env_checker import check_env

    env = gym.make(ENV_ID, config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle")
    assert isinstance(env.unwrapped, LandingEnv)
    check_env(env.unwrapped, skip_render_check=True)
    env = gym.make(ENV_ID, config="montecarlo_efference", overrides=QUIET, sites="H", estimator="oracle",
                   observation=["divergence", "oracle"], action="divergence_setpoint")
    check_env(env.unwrapped, skip_render_check=True)


def test_make_vec_and_batch_size_from_num_envs():
    envs = gym.make_vec(ENV_ID, num_envs=3, vectorization_mode="vector_entry_point", config="paper",
                        overrides=QUIET, sites="D,E", estimator="oracle", observation="oracle")
    assert envs.num_envs == 3 and envs.observation_space.shape == (3, 4) and envs.action_space.shape == (3, 1)
    # seed 0 of both sites and settings first: D x2 settings, then E
    assert envs.unwrapped.layout.site == ["D", "D", "E"]
    big = LandingVectorEnv(num_envs=6, config="paper", overrides=QUIET, sites="D", estimator="oracle",
                           observation="oracle")
    assert big.layout.batch_size == 6 and sorted(set(big.layout.seed_idx.tolist())) == [0, 1, 2]
    obs, _ = big.reset(seed=0)
    assert big.observation_space.contains(obs)


def test_bad_names_and_actions_raise():
    kw = dict(config="paper", overrides=QUIET, sites="D", estimator="oracle")
    with pytest.raises(ValueError, match=r"observation must be one of \['events', 'divergence', 'oracle'\]"):
        LandingVectorEnv(observation="depth", **kw)
    with pytest.raises(ValueError, match=r"action must be one of \['thrust', 'thrust_n', 'divergence_setpoint'\]"):
        LandingVectorEnv(observation="oracle", action="torque", **kw)
    env = LandingVectorEnv(observation="oracle", **kw)
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(np.zeros(env.num_envs))
    env.reset()
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(np.full(env.num_envs, np.nan))
    with pytest.raises(ValueError, match=r"action \('thrust'\) must be in \[-1, 1\]"):
        env.step(np.full(env.num_envs, 1.5))
    with pytest.raises(ValueError, match=r"action must have shape \(2,\)"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match=r"options: unknown keys \['mask'\]"):
        env.reset(options={"mask": np.ones(2, bool)})
    with pytest.raises(ValueError, match=r"options\['reset_mask'\] must be a \(2,\) bool array"):
        env.reset(options={"reset_mask": np.ones(3, bool)})
    with pytest.raises(ValueError, match=r"seed must be None, an int or 2 ints"):
        env.reset(seed=[1, 2, 3])
    with pytest.raises(ValueError, match="autoreset_mode must be one of"):
        LandingVectorEnv(observation="oracle", autoreset_mode="sometimes", **kw)
    with pytest.raises(ValueError, match="start_dispersion"):
        LandingVectorEnv(observation="oracle", start_dispersion=2.0, **kw)
    clip = LandingVectorEnv(observation="oracle", clip_actions=True, **kw)
    clip.reset()
    _, _, _, _, info = clip.step(np.full(clip.num_envs, 7.0))
    assert np.allclose(info["thrust_n"], clip.action_spec.thrust_high_n)
    with pytest.raises(ValueError, match="action must be finite"):
        clip.step(np.full(clip.num_envs, np.inf))


def test_seeding_is_deterministic_and_reseeds_the_dispersions():
    kw = dict(config="montecarlo_efference", overrides=QUIET + ["simulation.n_seeds=3"], sites="D",
              estimator="oracle", observation="oracle", action="thrust_n")
    a, b = LandingVectorEnv(**kw), LandingVectorEnv(**kw)
    obs_a, info_a = a.reset(seed=7)
    obs_b, info_b = b.reset(seed=7)
    np.testing.assert_array_equal(obs_a, obs_b)
    np.testing.assert_array_equal(info_a["z_m"], info_b["z_m"])
    for _ in range(20):
        obs_a, ra, *_ , info_a = a.step(info_a["controller_thrust_n"])
        obs_b, rb, *_ , info_b = b.step(info_b["controller_thrust_n"])
        np.testing.assert_array_equal(obs_a, obs_b)
        np.testing.assert_array_equal(ra, rb)
    obs_c, info_c = a.reset(seed=8)  # another master seed: other dispersed initial altitudes
    assert not np.array_equal(info_c["z_m"], info_b["z_m"])
    obs_d, _ = a.reset()  # no seed: the same descents again
    np.testing.assert_array_equal(obs_c, obs_d)


def _ends(env, n_max=5000):
    """Fly with the law's commands until some env ends; (step outputs of that step, next step's)."""
    obs, info = env.reset()
    for _ in range(n_max):
        res = env.step(np.nan_to_num(info["controller_thrust_n"]))
        obs, rew, term, trunc, info = res
        if (term | trunc).any():
            return res, env.step(np.nan_to_num(info["controller_thrust_n"]))
    raise AssertionError("no episode ended")


def test_next_step_autoreset_restarts_one_descent_while_the_other_flies():
    """D (Kp4e6-n10) ends before D (Kp5e6-n5): the step after its end returns its next episode's
    first observation (reward 0, flags False) while the other descent flies on; nobody waits."""
    env = LandingVectorEnv(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle",
                           action="thrust_n")
    assert env.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    (obs, rew, term, trunc, info), (obs2, rew2, term2, trunc2, info2) = _ends(env)
    i = int(np.flatnonzero(term | trunc)[0])
    j = 1 - i
    assert info["outcome"][i] == "success" and info["outcome"][j] == "running"
    assert info2["outcome"][i] == "reset" and rew2[i] == 0 and not (term2[i] or trunc2[i])
    assert info2["t_s"][i] == 0.0 and info2["episode"].tolist()[i] == 1 and info2["z_m"][i] > 3000
    assert info2["outcome"][j] == "running" and info2["t_s"][j] > info["t_s"][j]  # the other flies on
    obs3, rew3, *_, info3 = env.step(np.nan_to_num(info2["controller_thrust_n"]))
    assert info3["t_s"][i] == pytest.approx(0.1) and info3["z_m"][i] < info2["z_m"][i]  # its new episode flies


def test_same_step_autoreset_returns_the_next_episode_and_the_final_observation():
    env = LandingVectorEnv(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle",
                           action="thrust_n", autoreset_mode="same_step")
    (obs, rew, term, trunc, info), _ = _ends(env)
    i = int(np.flatnonzero(term | trunc)[0])
    assert info["_final_obs"][i] and not info["_final_obs"][1 - i]
    final = info["final_obs"][i]
    assert final.shape == (4,) and not np.array_equal(final, obs[i])
    assert info["final_info"][i]["outcome"] == "success" and info["final_info"][i]["z_m"] <= 50.0
    assert info["episode"][i] == 1 and info["t_s"][i] == 0.0 and env.observation_space.contains(obs)


def test_disabled_autoreset_and_reset_mask():
    env = LandingVectorEnv(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle",
                           action="thrust_n", autoreset_mode="disabled")
    (obs, rew, term, trunc, info), (obs2, rew2, term2, trunc2, info2) = _ends(env)
    i = int(np.flatnonzero(term | trunc)[0])
    j = 1 - i
    assert info2["outcome"][i] == "ended" and rew2[i] == 0 and info2["ignored"][i]
    np.testing.assert_array_equal(obs2[i], obs[i])  # frozen until reset
    z_j = info2["z_m"][j]
    mask = np.zeros(2, bool)
    mask[i] = True
    obs3, info3 = env.reset(options={"reset_mask": mask})
    assert info3["z_m"][i] > 3000 and info3["z_m"][j] == z_j  # only the masked env restarted
    np.testing.assert_array_equal(obs3[j], obs2[j])
    obs4, rew4, term4, trunc4, info4 = env.step(np.nan_to_num(info3["controller_thrust_n"]))
    assert not info4["ignored"].any() and info4["t_s"][i] == pytest.approx(0.1)


def test_seeds_change_the_descents_and_replay_them():
    env = LandingVectorEnv(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle")
    _, a = env.reset(seed=0)
    _, b = env.reset(seed=1)
    _, c = env.reset(seed=[0, 1])
    _, d = env.reset()
    assert not np.array_equal(a["z_m"], b["z_m"])
    np.testing.assert_array_equal(a["z_m"], c["z_m"])
    np.testing.assert_array_equal(c["z_m"], d["z_m"])


def test_reward_terminal_terms():
    env = LandingVectorEnv(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle",
                           action="thrust_n", reward={"tracking_weight": 0.0, "success_bonus": 5.0,
                                                      "speed_penalty": 1.0, "failure_penalty": 3.0},
                           start_dispersion=0.0)
    (outcome, _, _, ret), _ = fly_episode(env)
    assert outcome == ["success", "success"]
    obs, _ = env.reset()
    for _ in range(1000):  # free fall: a crash, nothing but the failure penalty without tracking
        obs, rew, term, trunc, info = env.step(np.zeros(2))
        assert env.observation_space.contains(obs)
        if term.all():
            break
    assert info["outcome"].tolist() == ["crash", "crash"] and rew.tolist() == [-3.0, -3.0]
    assert ((ret > 5.0 - 1.0 * 10) & (ret < 5.0)).all()  # bonus minus a few m/s at 50 m
    dense = LandingVectorEnv(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle",
                             start_dispersion=0.0)
    dense.reset()
    for _ in range(40):  # per step: dt max(0, 1 - |D - D*| / 0.02) at the step's end (the next observation's
        obs, rew, *_ = dense.step(np.full(2, -0.6))  # first two fields): falls from 0.1 as D leaves D*
        np.testing.assert_allclose(rew, 0.1 * np.maximum(0, 1 - np.abs(obs[:, 0] - obs[:, 1]) / 0.02), rtol=1e-4,
                                   atol=1e-7)
    assert 0 < rew[0] < 0.09


def test_divergence_setpoint_on_the_target_lands():
    """Set-point = the observed D*(t): the set-point law lands D on the oracle."""
    env = LandingVectorEnv(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle",
                           action="divergence_setpoint", num_envs=1)
    (outcome, t_end, _, _), _ = fly_episode(env, policy=lambda obs, info: obs[:, 1])
    assert outcome == ["success"]


def test_events_and_divergence_observations():
    env = LandingVectorEnv(config="paper", sites="D", estimator="cmax", num_envs=1,
                           overrides=QUIET + ["camera.width_px=64", "camera.height_px=64"],
                           observation=("events", "divergence"))
    obs, info = env.reset(seed=0)
    assert env.single_observation_space["events"].shape == (2, 64, 64)
    assert obs["events"].sum() == 0  # no events before the second frame
    for _ in range(35):
        obs, rew, term, trunc, info = env.step(np.zeros(1))
        assert env.observation_space.contains(obs)
    assert obs["events"].sum() > 0
    assert obs["divergence"][0, 1] > 0 and obs["divergence"][0, 0] < 0  # a confident negative D_hat


def test_sb3_adapter_of_the_training_example(repo_root):
    """dvsland.envs.sb3's stable-baselines3 VecEnv (used by scripts/train_policy_oracle.py): same-step
    autoreset (the end's observation in terminal_observation, the element's next episode returned)."""
    pytest.importorskip("stable_baselines3")
    import importlib.util

    path = repo_root / "scripts" / "train_policy_oracle.py"
    spec = importlib.util.spec_from_file_location("train_policy_oracle", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    env = LandingVectorEnv(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation="oracle",
                           autoreset_mode="same_step")
    from dvsland.envs.sb3 import sb3_vec_env

    venv = sb3_vec_env(env)
    obs0 = venv.reset()
    for _ in range(2000):
        venv.step_async(np.full((2, 1), -0.33))  # about hover: ends by the 200 s timeout at the latest
        obs, rew, done, infos = venv.step_wait()
        if done.any():
            break
    i = int(np.flatnonzero(done)[0])
    assert "terminal_observation" in infos[i] and infos[i]["outcome"] in ("success", "crash", "ascent", "timeout")
    assert obs[i][3] == 0.0 and obs0[i][3] == 0.0  # the returned observation starts the next episode (t = 0)
    assert infos[i]["terminal_observation"][3] > 0 and not np.array_equal(infos[i]["terminal_observation"], obs[i])


def test_bad_constructor_arguments_and_actions_are_named():
    """Each bad input is one ValueError naming it, before anything is built (issue: faults in the env)."""
    kw = dict(config="paper", sites="D", estimator="oracle", observation="oracle", overrides=QUIET)
    for bad, msg in ((dict(device="gpu0"), "device='gpu0' is not a torch device"),
                     (dict(num_envs=10 ** 9), r"num_envs must be an integer in \[1, 1000000\]"),
                     (dict(num_envs=True), "num_envs must be an integer"),
                     (dict(num_envs=400_000, estimator="cmax"), "num_envs=400000: simulation.max_memory_gb"),
                     (dict(overrides=[3]), "overrides must be 'section.key=value' strings")):
        with pytest.raises(ValueError, match=msg):
            LandingVectorEnv(**{**kw, **bad})
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device='cuda': CUDA is not available"):
            LandingVectorEnv(**{**kw, "device": "cuda"})
    env = LandingVectorEnv(**{**kw, "overrides": "simulation.t_max_s=2"})  # one override as a string
    assert env.cfg.simulation.t_max_s == 2.0
    env.reset()
    for a in (np.array(["0.5", "0.5"]), np.array([1j, 1j]), np.array([None, None]), np.array([True, False])):
        with pytest.raises(ValueError, match="action must be real numbers"):
            env.step(a)
    with pytest.raises(ValueError, match="seed must be an int in"):
        env.reset(seed=2 ** 70)


def test_torch_array_api_matches_numpy_and_stays_in_tensors():
    kw = dict(config="paper", overrides=QUIET, sites="D", estimator="oracle", observation=("oracle", "divergence"),
              action="thrust_n", autoreset_mode="same_step")
    a, t = LandingVectorEnv(**kw), LandingVectorEnv(**kw, array_api="torch")
    obs_a, info_a = a.reset(seed=3)
    obs_t, info_t = t.reset(seed=3)
    assert isinstance(obs_t["oracle"], torch.Tensor) and isinstance(info_t["z_m"], torch.Tensor)
    for _ in range(30):
        act = np.nan_to_num(info_a["controller_thrust_n"])
        obs_a, r_a, term_a, trunc_a, info_a = a.step(act)
        obs_t, r_t, term_t, trunc_t, info_t = t.step(torch.as_tensor(act))
        assert isinstance(r_t, torch.Tensor) and r_t.dtype == torch.float64 and term_t.dtype == torch.bool
        for n in obs_a:
            np.testing.assert_array_equal(obs_t[n].numpy(), obs_a[n])
        np.testing.assert_array_equal(r_t.numpy(), r_a)
        np.testing.assert_array_equal(info_t["z_m"].numpy(), info_a["z_m"])
    with pytest.raises(ValueError, match="array_api"):
        LandingVectorEnv(**kw, array_api="jax")
