"""The estimators ``dpr``, ``learned`` and ``snn`` as stages: params + State + pure step.

For each: the step is pure (the input state is left bit-identical; the same state stepped twice
gives the same outputs and next states), ``reset_where`` leaves the unmasked descents
bit-identical, a malformed State is a ValueError naming the stage and the field, the object API
(``update``/``reset``) and the contract agree, and the estimates equal, bit for bit, those the
estimators gave before the conversion (:data:`REFERENCE`, recorded on :func:`_scenario`).
"""

from __future__ import annotations

import math

import pytest
import torch

from dvsland.estimators import get_estimator
from dvsland.evaluate.synthetic import blob_layout, zoom_blob_events
from dvsland.events import Events
from dvsland.pytree import tree_clone, tree_equal, tree_leaves

NAN = math.nan
B = 4

#: the scenarios of REFERENCE: (estimator, sensor (W, H), scene: (n_blobs, events_per_blob), params)
SCENARIOS = {
    "dpr_default64": ("dpr", (64, 64), (12, 40), dict(n_min=10, radius_px=3.0)),
    "dpr_base3": ("dpr", (64, 64), (12, 40), dict(n_min=10, radius_px=3.0, baseline_steps=3, memory_ms=300.0)),
    "dpr_hot_len": ("dpr", (64, 64), (12, 40), dict(n_min=8, radius_px=2.5, hot_pixel_factor=4.0,
                                                     pair_weighting="length", merge_px=0.0)),
    "learned_cnn": ("learned", (128, 128), (20, 60), {}),
    "learned_spiking": ("learned", (128, 128), (20, 60), dict(checkpoint="spiking")),
    "snn": ("snn", (128, 128), (20, 60), dict(warmup_steps=2)),
}
#: step -> reset mask before it (None = every descent)
RESETS = {5: [False, True, False, False], 15: [True, False, False, True], 19: None}


def _scenario(sensor, n_blobs, events_per_blob, n_steps=24):
    """[(events, t_us)] of 24 steps of B = 4 zooming blob fields (D from -0.4 to -0.1 1/s); descent
    1 has no events at steps 7 and 8, no descent at step 12."""
    off = blob_layout(B, n_blobs, sensor, seed=0)
    div = torch.linspace(-0.4, -0.1, B).double()
    out = []
    for k in range(n_steps):
        t0, t1 = k * 100_000, (k + 1) * 100_000
        active = torch.ones(B, dtype=torch.bool)
        if k in (7, 8):
            active[1] = False
        ev = Events.empty() if k == 12 else zoom_blob_events(off, div, t0, t1, sensor, events_per_blob=events_per_blob,
                                                             seed=k, active=active)
        out.append((ev, t1))
    return out


#: D_hat (B = 4) at each of the 24 steps of :func:`_scenario`, recorded with the estimators as they were
#: before the stage contract (object API, attributes as state); float32 values written exactly
REFERENCE = {
    'dpr_default64': [
        NAN, NAN, NAN, NAN, -0.3646855354309082, -0.31380173563957214, -0.20537465810775757, -0.11235883831977844,
        -0.41236448287963867, -0.33693626523017883, -0.18008007109165192, -0.10190426558256149, -0.40279170870780945,
        -0.3048327565193176, -0.21772082149982452, -0.09682264178991318, -0.34368330240249634, -0.31606537103652954,
        -0.2099369466304779, -0.08493703603744507, -0.4006282389163971, NAN, -0.20323650538921356,
        -0.09755917638540268, -0.4165671169757843, -0.2712215483188629, -0.20016267895698547, -0.09775710105895996,
        -0.39407649636268616, 0.0, -0.20935070514678955, -0.10158708691596985, -0.41251009702682495, 0.0,
        -0.20131807029247284, -0.0934862494468689, -0.3470909893512726, -0.5115358829498291, -0.1916293203830719,
        -0.10206813365221024, -0.3997914791107178, -0.5748641490936279, -0.20916618406772614, -0.10113319754600525,
        -0.4138912260532379, -0.4742218255996704, -0.20779506862163544, -0.09593146294355392, -0.23965419828891754,
        0.0, -0.10981433838605881, -0.041439928114414215, -0.30772101879119873, -0.18890655040740967,
        -0.261600524187088, -0.134219691157341, -0.5087792873382568, -0.4137316346168518, -0.2523651123046875,
        -0.11920458823442459, NAN, -0.39240407943725586, -0.2407514899969101, NAN, -0.4587038457393646,
        -0.3430000841617584, -0.24665440618991852, -0.09069982916116714, -0.44858044385910034, -0.165657177567482,
        -0.10290439426898956, -0.0980241447687149, -0.43208616971969604, -0.3012396991252899, -0.20080795884132385,
        -0.08839988708496094, NAN, NAN, NAN, NAN, -0.4728236794471741, -0.3552541732788086, -0.18914976716041565,
        -0.13307805359363556, -0.4608634412288666, -0.2885255813598633, -0.20113711059093475, -0.15307855606079102,
        -0.42912721633911133, -0.29891353845596313, -0.18528079986572266, -0.09710033982992172, -0.4161841571331024,
        -0.27799370884895325, -0.19889196753501892, -0.1093495562672615,
    ],
    'dpr_base3': [
        NAN, NAN, NAN, NAN, -0.36016950011253357, -0.3085241913795471, -0.18705734610557556, -0.11267440766096115,
        -0.3858886659145355, -0.324075311422348, -0.18688973784446716, -0.1092180386185646, -0.389133095741272,
        -0.3185836970806122, -0.1932959407567978, -0.10651496797800064, -0.3969584107398987, -0.307695597410202,
        -0.2038775533437729, -0.09792696684598923, -0.4035639762878418, NAN, -0.20917198061943054,
        -0.09209141135215759, -0.3953927755355835, -0.2674124538898468, -0.20968930423259735, -0.0903477892279625,
        -0.3869490921497345, -0.1337062269449234, -0.19421668350696564, -0.09871388226747513, -0.37433499097824097,
        -0.13265860080718994, -0.18880489468574524, -0.10433312505483627, -0.3847779631614685, -0.3949503004550934,
        -0.1931668370962143, -0.10038013756275177, -0.389547735452652, -0.3780341148376465, -0.20457977056503296,
        -0.0980186015367508, -0.3992913067340851, -0.3930714726448059, -0.20863914489746094, -0.09303764253854752,
        -0.3349422812461853, -0.1543247252702713, -0.17545273900032043, -0.07683049887418747, -0.4034436345100403,
        -0.26100635528564453, -0.20288631319999695, -0.09696554392576218, -0.46933552622795105, -0.3526487648487091,
        -0.22817671298980713, -0.12328382581472397, NAN, -0.3447246551513672, -0.22674693167209625, NAN,
        -0.4678019881248474, -0.2921687364578247, -0.19645185768604279, -0.0677981972694397, -0.4491625726222992,
        -0.2479798048734665, -0.16459552943706512, -0.085232213139534, -0.4416203796863556, -0.30747631192207336,
        -0.20221230387687683, -0.08503679186105728, NAN, NAN, NAN, NAN, -0.4599687159061432, -0.3211445212364197,
        -0.20270507037639618, -0.11496838182210922, -0.45236659049987793, -0.3028387129306793, -0.20269326865673065,
        -0.13341160118579865, -0.4258791208267212, -0.30417725443840027, -0.19832037389278412, -0.12174409627914429,
        -0.37957924604415894, -0.2989043593406677, -0.20239701867103577, -0.12102940678596497,
    ],
    'dpr_hot_len': [
        NAN, NAN, NAN, NAN, -0.37333086133003235, -0.3030838668346405, -0.19143754243850708, -0.1040087416768074,
        -0.3800375461578369, -0.3331758379936218, -0.19005487859249115, -0.1005498394370079, -0.3432779908180237,
        -0.29279816150665283, -0.2052907794713974, -0.09484798461198807, -0.2501278221607208, -0.2401825338602066,
        -0.20044615864753723, -0.07933835685253143, -0.35477328300476074, NAN, -0.20357339084148407,
        -0.0939960852265358, -0.3939427435398102, -0.27305781841278076, -0.19618546962738037, -0.1007976084947586,
        -0.42223671078681946, 0.0, -0.2076190710067749, -0.10099462419748306, -0.41465944051742554, 0.0,
        -0.2033676654100418, -0.09319254755973816, -0.3545122742652893, -0.336110383272171, -0.1861506700515747,
        -0.09817563742399216, -0.3795351982116699, -0.4716658890247345, -0.20354785025119781, -0.09923737496137619,
        -0.42262375354766846, -0.672264575958252, -0.21379931271076202, -0.08621157705783844, -0.26253461837768555,
        0.0, -0.10579966753721237, -0.046026308089494705, -0.2672118842601776, -0.142618328332901,
        -0.25104692578315735, -0.13254137337207794, -0.3783814013004303, -0.3413560390472412, -0.2651980519294739,
        -0.12727141380310059, NAN, -0.4600985646247864, -0.2480352520942688, NAN, -0.4681895971298218,
        -0.3472442328929901, -0.23895174264907837, -0.08037803322076797, -0.45940980315208435, -0.15365813672542572,
        -0.10657089948654175, -0.09980906546115875, -0.380079448223114, -0.2626187801361084, -0.19616316258907318,
        -0.09885790944099426, NAN, NAN, NAN, NAN, -0.46851375699043274, -0.31956762075424194, -0.2200562208890915,
        -0.12995146214962006, -0.3930343985557556, -0.2894573509693146, -0.19796259701251984, -0.14652958512306213,
        -0.3509104549884796, -0.28436997532844543, -0.18153879046440125, -0.10226565599441528, -0.23950016498565674,
        -0.26710963249206543, -0.16630512475967407, -0.10779932141304016,
    ],
    'learned_cnn': [
        -0.05096564441919327, -0.036366235464811325, -0.03360503911972046, -0.022519873455166817,
        -0.08677772432565689, -0.03686130419373512, -0.04488212615251541, -0.025898847728967667,
        -0.10003278404474258, -0.05443168804049492, -0.06521844863891602, -0.033400632441043854,
        -0.08358903229236603, -0.0632215365767479, -0.0623675212264061, -0.030259227380156517, -0.08106456696987152,
        -0.06910458952188492, -0.06706192344427109, -0.029446355998516083, -0.09329673647880554,
        -0.020017946138978004, -0.05854980647563934, -0.028699709102511406, -0.12315604090690613,
        -0.02981071174144745, -0.0658818706870079, -0.029211832210421562, -0.13696008920669556, NAN,
        -0.07154222577810287, -0.02889995463192463, -0.12146498262882233, NAN, -0.07173289358615875,
        -0.028742754831910133, -0.12772709131240845, -0.03593069687485695, -0.06479554623365402,
        -0.02986786887049675, -0.10980834811925888, -0.05298006907105446, -0.06893257796764374, -0.03347723186016083,
        -0.12269911915063858, -0.09470455348491669, -0.07222927361726761, -0.033545490354299545, NAN, NAN, NAN, NAN,
        -0.10627824068069458, -0.06732095777988434, -0.06233564764261246, -0.029651930555701256, -0.1139916181564331,
        -0.07769787311553955, -0.06729765981435776, -0.028949635103344917, -0.024241207167506218,
        -0.09294527769088745, -0.06485094130039215, -0.0196017287671566, -0.046412404626607895, -0.11760345101356506,
        -0.05998748168349266, -0.03423561528325081, -0.06260999292135239, -0.08964982628822327, -0.06277146190404892,
        -0.03546573966741562, -0.05906879901885986, -0.07104194909334183, -0.07265756279230118, -0.03980499878525734,
        -0.011806967668235302, -0.012814795598387718, -0.03188476338982582, -0.025625839829444885,
        -0.01970052532851696, -0.004103001207113266, -0.07463160157203674, -0.030042758211493492,
        -0.04157164692878723, -0.0178424883633852, -0.08133602887392044, -0.042033206671476364, -0.0435541532933712,
        -0.0199214369058609, -0.06778724491596222, -0.03506825864315033, -0.05250917747616768, -0.02251383289694786,
        -0.06437403708696365, -0.035899288952350616,
    ],
    'learned_spiking': [
        -0.5879480838775635, -0.5879480838775635, -0.5879480838775635, -0.5879480838775635, -0.4372031092643738,
        -0.4061909317970276, -0.47466254234313965, -0.4956950843334198, -0.34131860733032227, -0.22395409643650055,
        -0.3480619788169861, -0.3867019712924957, -0.3075540363788605, -0.216426283121109, -0.31427645683288574,
        -0.49889156222343445, -0.41140976548194885, -0.21262899041175842, -0.26288697123527527, -0.4301306903362274,
        -0.41444137692451477, -0.5610531568527222, -0.276719331741333, -0.46036043763160706, -0.3188905715942383,
        -0.40787503123283386, -0.2762145400047302, -0.4844966530799866, -0.3382144570350647, NAN,
        -0.2819387912750244, -0.5362162590026855, -0.25952956080436707, NAN, -0.29564887285232544,
        -0.4094296395778656, -0.2664964199066162, -0.2552679777145386, -0.31098031997680664, -0.41674450039863586,
        -0.25012242794036865, -0.39948949217796326, -0.47428426146507263, -0.41310250759124756, -0.2894277274608612,
        -0.3066287338733673, -0.46434736251831055, -0.3655436038970947, NAN, NAN, NAN, NAN, -0.22763830423355103,
        -0.29016008973121643, -0.1997930407524109, -0.3483634889125824, -0.2925795018672943, -0.2622857093811035,
        -0.30073872208595276, -0.3155922591686249, -0.44339340925216675, -0.24357932806015015, -0.34131112694740295,
        -0.5879480838775635, -0.38407281041145325, -0.23051808774471283, -0.34403201937675476, -0.46572041511535645,
        -0.2813990116119385, -0.233120396733284, -0.3005373179912567, -0.288923054933548, -0.26711827516555786,
        -0.26471003890037537, -0.2669714689254761, -0.2959408462047577, -0.23815305531024933, -0.28579115867614746,
        -0.48244163393974304, -0.5879480838775635, -0.30659452080726624, -0.31890061497688293, -0.4749106764793396,
        -0.5765780806541443, -0.2822067439556122, -0.30699726939201355, -0.3551810085773468, -0.372601181268692,
        -0.34745538234710693, -0.32893607020378113, -0.35866859555244446, -0.29459962248802185, -0.31229767203330994,
        -0.27644526958465576, -0.38585227727890015, -0.2996824085712433,
    ],
    'snn': [
        NAN, NAN, NAN, NAN, NAN, NAN, NAN, NAN, -0.01060465443879366, -0.008417345583438873, -0.010766133666038513,
        -0.00978852342814207, -0.02444572187960148, -0.018343554809689522, -0.022561248391866684,
        -0.02195403352379799, -0.03693610429763794, -0.02714192308485508, -0.03386218100786209, -0.03229430317878723,
        -0.046475883573293686, NAN, -0.04290332272648811, -0.03852679580450058, -0.05327364429831505, NAN,
        -0.05053303390741348, -0.04308288171887398, -0.05948967486619949, -0.00797637552022934, -0.05744248256087303,
        -0.04562876746058464, -0.06510760635137558, -0.015428661368787289, -0.06339205056428909, -0.0453006885945797,
        -0.07063769549131393, -0.020680615678429604, -0.06840696185827255, -0.04545603320002556,
        -0.07347281277179718, -0.02174069732427597, -0.07218017429113388, -0.04553299397230148, -0.07662812620401382,
        -0.02523391880095005, -0.07665394991636276, -0.04603445529937744, -0.07858901470899582, -0.03024502471089363,
        -0.08100975304841995, -0.045735277235507965, -0.07851000875234604, -0.034278202801942825,
        -0.08415206521749496, -0.0423077754676342, -0.0743403434753418, -0.03628695383667946, -0.08361571282148361,
        -0.03959184139966965, NAN, -0.03725076839327812, -0.08224885910749435, NAN, NAN, -0.03843817487359047,
        -0.08232281357049942, NAN, -0.0056029194965958595, -0.039049044251441956, -0.0845266804099083,
        -0.008217562921345234, -0.009437702596187592, -0.0390484556555748, -0.08646903187036514,
        -0.01677844487130642, NAN, NAN, NAN, NAN, NAN, NAN, NAN, NAN, -0.005668424069881439, -0.005489159841090441,
        -0.008377625606954098, -0.008496544323861599, -0.00866200216114521, -0.008303041569888592,
        -0.016566528007388115, -0.016202528029680252, -0.011668882332742214, -0.01006958819925785,
        -0.023888101801276207, -0.021365974098443985,
    ],
}


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Bit-identical tensors (NaN equals NaN)."""
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if a.is_floating_point():
        return torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(-7.0), b.nan_to_num(-7.0))
    return torch.equal(a, b)


@pytest.mark.parametrize("name", sorted(REFERENCE))
def test_estimates_equal_those_before_the_stage_contract(name, recording_cpu):
    """The object API (update / reset) on the scenario: D_hat bit for bit as recorded (on another CPU,
    whose convolutions and sums may round differently, within float32 rounding of the record)."""
    est_name, sensor, (n_blobs, epb), params = SCENARIOS[name]
    est = get_estimator(est_name, B, sensor, **params)
    got = []
    for k, (ev, t) in enumerate(_scenario(sensor, n_blobs, epb)):
        if k in RESETS:
            est.reset(None if RESETS[k] is None else torch.tensor(RESETS[k]))
        got.append(est.update(ev, t))
    got = torch.stack(got)
    want = torch.tensor(REFERENCE[name], dtype=torch.float32).view_as(got)
    close = torch.equal(got.isnan(), want.isnan()) and torch.allclose(got.nan_to_num(0), want.nan_to_num(0),
                                                                       rtol=1e-4, atol=1e-6)
    assert _same(got, want) or (close and not recording_cpu), \
        f"{name}: max |diff| {(got - want).abs().nan_to_num(0).max()}"


# ------------------------------------------------------------------ the contract, per stage
STAGES = {
    "dpr": lambda: get_estimator("dpr", B, (64, 64), n_min=10, radius_px=3.0, baseline_steps=2),
    "learned": lambda: get_estimator("learned", B, (128, 128), min_events=5),
    "learned_spiking": lambda: get_estimator("learned", B, (96, 80), checkpoint="spiking", min_events=5),
    "snn": lambda: get_estimator("snn", B, (128, 128), warmup_steps=1, max_silent_steps=2),
}
#: fields a restart keeps (clocks and positions shared by every descent)
KEPT = {"dpr": ("last_t_us",), "learned": ("newest", "t_prev_us"), "learned_spiking": ("newest", "t_prev_us"),
        "snn": ("t_prev_us",)}
SENSORS = {"dpr": (64, 64), "learned": (128, 128), "learned_spiking": (96, 80), "snn": (128, 128)}


def _stage_and_steps(stage, n=6):
    est = STAGES[stage]()
    n_blobs, epb = (12, 40) if stage == "dpr" else (16, 50) if SENSORS[stage] == (96, 80) else (20, 60)
    return est, _scenario(SENSORS[stage], n_blobs, epb, n_steps=n)


def _run(est, state, steps):
    outs = []
    for ev, t in steps:
        state, out = est.step_state(state, ev, t)
        outs.append(out)
    return state, outs


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_step_is_pure(stage):
    est, steps = _stage_and_steps(stage)
    state, _ = _run(est, est.init_state(), steps[:-1])
    before = tree_clone(state)
    ev, t = steps[-1]
    s1, o1 = est.step_state(state, ev, t)
    assert tree_equal(state, before), "step_state wrote into its input state"
    s2, o2 = est.step_state(state, ev, t)
    assert tree_equal(s1, s2) and tree_equal(o1, o2)
    assert not any(a is b for a, b in zip(tree_leaves(s1).values(), tree_leaves(state).values()))


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_object_api_is_the_contract(stage):
    """update / reset / diagnostics over the held state give what the pure steps give."""
    est, steps = _stage_and_steps(stage)
    state = est.init_state()
    mask = torch.tensor([False, True, False, True])
    for k, (ev, t) in enumerate(steps):
        if k == 3:
            est.reset(mask)
            state = est.reset_where(state, mask)
        d = est.update(ev, t)
        state, out = est.step_state(state, ev, t)
        assert _same(d, out.d_hat) and _same(est.confidence(), out.confidence)
    assert tree_equal(est.state, state)
    diag = est.diagnostics()
    assert "confidence" in diag and tree_equal({k: diag[k] for k in out.diagnostics}, out.diagnostics)


def _row(tree, i):
    return {k: v[i] for k, v in tree_leaves(tree).items() if not k.endswith("_packed")}


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_reset_where_leaves_the_others_bit_identical(stage):
    est, steps = _stage_and_steps(stage)
    state, _ = _run(est, est.init_state(), steps)
    mask = torch.tensor([False, True, True, False])
    new = est.reset_where(state, mask)
    fresh = est.init_state()
    for i in range(B):
        want = _row(fresh, i) if mask[i] else _row(state, i)
        if mask[i]:
            want.update({k: getattr(state, k)[i] for k in KEPT[stage]})
        assert tree_equal(_row(new, i), want), i
    assert tree_equal(est.reset_where(state, torch.zeros(B, dtype=torch.bool)), state)
    # after the reset, the unmasked descents go on as if nothing happened
    ev, t = steps[0][0], steps[-1][1] + 100_000
    _, a = est.step_state(new, ev, t)
    _, b = est.step_state(state, ev, t)
    keep = ~mask
    assert _same(a.d_hat[keep], b.d_hat[keep])


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_bad_state_names_stage_and_field(stage):
    est, steps = _stage_and_steps(stage, n=1)
    state = est.init_state()
    name, leaf = next((k, v) for k, v in tree_leaves(state).items() if v.dim() >= 1 and not k.endswith("_packed"))
    bad = state._replace(**{name: leaf.to(torch.float16 if leaf.dtype != torch.float16 else torch.float32)}) \
        if "." not in name else None
    if bad is not None:
        with pytest.raises(ValueError, match=rf"{stage.split('_')[0]}.*{name}.*dtype"):
            est.step_state(bad, *steps[0])
    short = state._replace(**{name: leaf[:-1]}) if "." not in name else None
    if short is not None:
        with pytest.raises(ValueError, match=rf"{stage.split('_')[0]}.*{name}.*shape"):
            est.step_state(short, *steps[0])
    with pytest.raises(ValueError, match=stage.split("_")[0]):
        est.step_state(tuple(state), *steps[0])


# ------------------------------------------------------------------ dpr specifics
def test_dpr_ring_is_packed_events_that_leave_after_k_steps_or_a_reset():
    est, steps = _stage_and_steps("dpr")
    state, _ = _run(est, est.init_state(), steps)
    plane = state.window.shape[1] * state.window.shape[2]
    K = est.n_ring
    b = state.ring_packed // plane
    assert state.ring_packed.shape[0] == int(state.window.sum()) == int(state.ring_counts.sum())
    assert torch.equal(torch.bincount(b, minlength=B), state.ring_counts.sum(1))
    assert torch.equal(torch.bincount(b[:int(state.ring_counts[:, 0].sum())], minlength=B), state.ring_counts[:, 0])
    mask = torch.tensor([True, False, False, True])
    new = est.reset_where(state, mask)
    assert not mask[new.ring_packed // plane].any() and (new.window[mask] == 0).all()
    assert torch.equal(new.ring_packed, state.ring_packed[~mask[b]]) and (new.ring_counts[mask] == 0).all()
    for k in range(K):
        new, _ = est.step_state(new, Events.empty(), steps[-1][1] + (k + 1) * 100_000)
    assert new.ring_packed.shape[0] == 0 and (new.window == 0).all() and (new.ring_counts == 0).all()


def test_dpr_dt_is_the_time_since_the_last_step():
    """A longer interval than dt_s halves Eq. 8's D (the same centroid motion over twice the time)."""
    est, steps = _stage_and_steps("dpr", n=8)
    state, _ = _run(est, est.init_state(), steps[:-1])
    ev, t = steps[-1]
    _, a = est.step_state(state, ev, t)
    assert torch.equal(state.last_t_us, torch.full((B,), steps[-2][1]))
    late = state._replace(last_t_us=state.last_t_us - 100_000)
    _, b = est.step_state(late, ev, t)
    ok = torch.isfinite(a.d_hat)
    assert ok.any() and not _same(a.d_hat[ok], b.d_hat[ok])


@pytest.mark.parametrize("name", ["dpr", "learned"])
def test_estimators_that_accept_donate_give_the_pure_steps_outputs(name):
    """step_state(..., donate=True) of an estimator that says ``accepts_donate``: the same next state
    and estimate as the pure step, step after step, the donated state's buffers reused."""
    est, steps = _stage_and_steps(name)
    assert est.accepts_donate
    pure = donated = est.init_state()
    for ev, t in steps:
        pure, a = est.step_state(pure, ev, t)
        given = donated
        donated, b = est.step_state(donated, ev, t, donate=True)
        assert tree_equal(pure, donated) and tree_equal(a, b)
        held = "window" if name == "dpr" else "ring"
        assert getattr(donated, held) is getattr(given, held)  # worked in place


# ------------------------------------------------------------------ learned specifics
def test_learned_donate_writes_the_ring_in_place_with_the_same_estimates():
    est, steps = _stage_and_steps("learned")
    state, _ = _run(est, est.init_state(), steps[:-1])
    keep = tree_clone(state)
    ev, t = steps[-1]
    pure, a = est.step_state(state, ev, t)
    assert tree_equal(state, keep)
    donated, b = est.step_state(state, ev, t, donate=True)
    assert donated.ring is state.ring and not torch.equal(state.ring, keep.ring)  # written in place
    assert tree_equal(pure, donated) and tree_equal(a, b)
    obj = get_estimator("learned", B, (128, 128), min_events=5, donate=True)
    for ev, t in steps:
        d = obj.update(ev, t)
    assert _same(d, a.d_hat) and tree_equal(obj.state, pure)


def test_learned_object_api_donates_its_own_ring_by_default():
    """update writes the held ring in place (the object owns it); donate=False copies it; same numbers."""
    default = get_estimator("learned", B, (128, 128), min_events=5)
    copying = get_estimator("learned", B, (128, 128), min_events=5, donate=False)
    _, steps = _stage_and_steps("learned")
    for ev, t in steps[:-1]:
        default.update(ev, t)
        copying.update(ev, t)
    ring_d, ring_c = default.state.ring, copying.state.ring
    ev, t = steps[-1]
    d_default, d_copying = default.update(ev, t), copying.update(ev, t)
    assert default.state.ring is ring_d and copying.state.ring is not ring_c
    assert _same(d_default, d_copying) and tree_equal(default.state, copying.state)


def test_learned_ring_position_is_shared_and_kept_by_a_restart():
    est, steps = _stage_and_steps("learned", n=3)
    state, _ = _run(est, est.init_state(), steps)
    K = est.spec.n_windows
    assert (state.newest == (K - 1 + 3) % K).all()
    new = est.reset_where(state, torch.tensor([True, False, True, False]))
    assert torch.equal(new.newest, state.newest) and (new.ring[0] == 0).all() and (new.ring_counts[2] == 0).all()


# ------------------------------------------------------------------ snn specifics
def test_snn_state_holds_the_lif_states_and_counters():
    est, steps = _stage_and_steps("snn", n=3)
    state, outs = _run(est, est.init_state(), steps)
    assert set(state.net._fields) == {"l1", "l2", "out"} and state.net.l1.v.shape[0] == B
    assert state.steps.tolist() == [3] * B and (state.t_prev_us == steps[-1][1]).all()
    for k in ("spikes", "synops", "events_in_annulus", "dropped_events", "spike_rate1"):
        assert k in outs[-1].diagnostics
    new = est.reset_where(state, torch.tensor([False, True, False, False]))
    assert (new.net.l1.v[1] == 0).all() and new.steps.tolist() == [3, 0, 3, 3]
    # the encoder keeps nothing: the pure step does not touch its attributes
    before = (est.encoder.dropped, est.encoder.events_in_annulus)
    est.step_state(state, *steps[0])
    assert (est.encoder.dropped, est.encoder.events_in_annulus) == before
