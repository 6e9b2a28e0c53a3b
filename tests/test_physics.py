"""Every equation of the system model against numbers worked out by hand from the paper.

The expected values are computed in the tests themselves with the `math` module, step by
step from the formulas in the paper (and docs/model.md#decisions), never by calling the function
under test; a few results are also pinned as literals so that a shared mistake in both the
code and the hand arithmetic cannot pass unnoticed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim import physics
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import RewardWeights, ScenarioConfig

CFG = ScenarioConfig()
TABLES = physics.Tables.from_config(CFG)
NOISE_W = 10 ** ((-120.0 - 30.0) / 10.0)  # -120 dBm = 1e-15 W


def dbm(p_dbm: float) -> float:
    return 10 ** ((p_dbm - 30.0) / 10.0)


def hand_hover_w() -> float:
    """Eq. (hover) with Gong et al.'s parameter set (docs/model.md#hover-power), written out term by term."""
    n_rotors = 4
    w_r = 20.0 / 4  # N per rotor
    rho, s, area, c_t, delta, k = 1.168, 0.045, 0.214, 0.001195, 0.011, 0.11
    profile = (1 / math.sqrt(rho)) * s * (1 / math.sqrt(area)) * c_t ** (-1.5) * delta / 8
    induced = (1 + k) / math.sqrt(2 * rho * area)
    return n_rotors * w_r**1.5 * (profile + induced)


# ------------------------------------------------------------------ units and geometry
def test_unit_conversions():
    assert physics.dbm_to_w(14.0) == pytest.approx(0.025118864315095794, rel=1e-12)
    assert physics.dbm_to_w(30.0) == pytest.approx(1.0, rel=1e-12)
    assert physics.dbm_to_w(-120.0) == pytest.approx(1e-15, rel=1e-12)
    assert physics.lin_to_db(100.0) == pytest.approx(20.0)
    # "no signal" is a finite floor, not -inf
    assert physics.lin_to_db(0.0) == physics.DB_FLOOR
    assert np.isfinite(physics.lin_to_db(np.array([0.0, -1.0, 1e-300]))).all()


def test_uav_positions_evenly_on_the_mid_line():
    # x_i = (i + 0.5) L / U, y = L / 2
    np.testing.assert_allclose(physics.uav_positions(CFG), [[250.0, 500.0], [750.0, 500.0]])
    four = CFG.replace(n_uavs=4, area_m=800.0)
    np.testing.assert_allclose(physics.uav_positions(four), [[100, 400], [300, 400], [500, 400], [700, 400]])


def test_horizontal_distance_by_hand():
    uav = np.array([[0.0, 0.0], [10.0, 0.0]])
    eds = np.array([[3.0, 4.0], [10.0, 0.0], [-6.0, -8.0]])
    d2 = physics.horizontal_distance_sq(eds, uav)
    assert d2.shape == (2, 3)  # [U, V]
    expected = [[5.0, 10.0, 10.0], [math.hypot(7, 4), 0.0, math.hypot(16, 8)]]
    np.testing.assert_allclose(d2, np.square(expected), rtol=1e-12)
    # leading batch dimension
    batch = physics.horizontal_distance_sq(np.stack([eds, eds[::-1]]), uav)
    assert batch.shape == (2, 2, 3)
    np.testing.assert_allclose(np.sqrt(batch[1]), np.array(expected)[:, ::-1], rtol=1e-12)


# ------------------------------------------------------------------ channel, Eqs. (plos), (a2g_pl)
def test_path_loss_right_under_the_uav_by_hand():
    h, f, c, a, b = 90.0, 868e6, 3e8, 4.88, 0.43
    d_h = 0.0
    d3 = math.sqrt(d_h**2 + h**2)  # 3-D distance (docs/model.md#channel) = 90 m
    assert d3 == 90.0
    fspl = 20 * math.log10(4 * math.pi * f * d3 / c)  # 4 pi 868e6 90 / 3e8 = 3272.28 -> 70.2970 dB
    assert fspl == pytest.approx(70.2970, abs=1e-4)
    theta = math.degrees(math.atan2(h, d_h))  # 90 degrees straight up
    assert theta == 90.0
    p_los = 1 / (1 + a * math.exp(-b * (theta - a)))  # exp(-36.6) -> P_LoS = 1 - 6e-16
    assert p_los == pytest.approx(1.0, abs=1e-12)
    total = fspl + 0.1 * p_los + 21.0 * (1 - p_los)
    assert total == pytest.approx(70.3970, abs=1e-4)

    assert physics.elevation_deg(d_h, CFG) == pytest.approx(theta, abs=1e-12)
    assert physics.los_probability(theta, CFG) == pytest.approx(p_los, abs=1e-12)
    assert physics.path_loss_db(d_h, CFG) == pytest.approx(total, abs=1e-9)
    assert physics.channel_gain(d_h, CFG) == pytest.approx(10 ** (-total / 10), rel=1e-9)
    assert np.isfinite(physics.path_loss_db(np.zeros(3), CFG)).all()


def test_path_loss_at_600_m_by_hand():
    h, f, c, a, b = 90.0, 868e6, 3e8, 4.88, 0.43
    d_h = 600.0
    d3 = math.sqrt(600.0**2 + 90.0**2)  # sqrt(368100) = 606.713 m
    assert d3 == pytest.approx(606.7125, abs=1e-4)
    fspl = 20 * math.log10(4 * math.pi * f * d3 / c)  # 86.8718 dB
    assert fspl == pytest.approx(86.8718, abs=1e-4)
    theta = math.degrees(math.atan(h / d_h))  # atan(0.15) = 8.5308 degrees
    assert theta == pytest.approx(8.5308, abs=1e-4)
    p_los = 1 / (1 + a * math.exp(-b * (theta - a)))  # 1 / (1 + 4.88 exp(-1.5697)) = 0.4962
    assert p_los == pytest.approx(0.4962, abs=1e-4)
    total = fspl + 0.1 * p_los + 21.0 * (1 - p_los)  # 86.8718 + 0.0496 + 10.580 = 97.5018
    assert total == pytest.approx(97.50, abs=0.01)

    assert physics.elevation_deg(d_h, CFG) == pytest.approx(theta, abs=1e-10)
    assert physics.los_probability(theta, CFG) == pytest.approx(p_los, abs=1e-12)
    got = physics.path_loss_db(np.array([0.0, 150.0, 600.0]), CFG)
    assert got[2] == pytest.approx(total, abs=1e-9)
    assert got[0] < got[1] < got[2]  # loss grows with distance
    assert physics.channel_gain(d_h, CFG) == pytest.approx(10 ** (-total / 10), rel=1e-9)


def test_path_loss_follows_the_config():
    # altitude, carrier and eta's are read from the config, not hard-coded
    cfg = CFG.replace(altitude_m=120.0, carrier_hz=433e6, eta_los_db=1.0, eta_nlos_db=20.0, los_a=9.61, los_b=0.16)
    d_h = 300.0
    d3 = math.hypot(300.0, 120.0)
    theta = math.degrees(math.atan2(120.0, 300.0))
    p_los = 1 / (1 + 9.61 * math.exp(-0.16 * (theta - 9.61)))
    total = 20 * math.log10(4 * math.pi * 433e6 * d3 / 3e8) + 1.0 * p_los + 20.0 * (1 - p_los)
    assert physics.path_loss_db(d_h, cfg) == pytest.approx(total, abs=1e-9)


# ------------------------------------------------------------------ LoRa thresholds
PAPER_THRESHOLDS = [  # the paper's Table "SNR rho_thr(Psi, W) in dB", cell by cell
    (7, 125, -7.5), (8, 125, -10.0), (9, 125, -12.5), (10, 125, -15.0), (11, 125, -18.0), (12, 125, -21.0),
    (7, 250, -9.0), (8, 250, -12.0), (9, 250, -14.5), (10, 250, -17.0), (11, 250, -20.0), (12, 250, -23.0),
    (7, 500, -11.0), (8, 500, -13.8), (9, 500, -16.5), (10, 500, -19.0), (11, 500, -21.8), (12, 500, -25.0),
]  # fmt: skip


@pytest.mark.parametrize("sf,bw,expected", PAPER_THRESHOLDS)
def test_snr_threshold_table_cell(sf, bw, expected):
    assert float(physics.snr_threshold_db(sf, bw)) == expected
    # and the per-scenario table indexed by (sf_idx, bw_idx) holds the same cell
    assert TABLES.threshold_db[CFG.sf_set.index(sf), CFG.bw_khz.index(bw)] == expected


def test_snr_threshold_vectorised_and_reduced_sets():
    sf = np.array([[7, 12], [9, 10]])
    bw = np.array([[500, 125], [250, 250]])
    np.testing.assert_array_equal(physics.snr_threshold_db(sf, bw), [[-11.0, -21.0], [-14.5, -17.0]])
    reduced = CFG.replace(sf_set=[12, 9], bw_khz=[500])  # sorted by the config: (9, 12) x (500,)
    np.testing.assert_array_equal(physics.Tables.from_config(reduced).threshold_db, [[-16.5], [-25.0]])


@pytest.mark.parametrize("sf,bw,field", [(6, 125, "sf"), (13, 125, "sf"), (7, 200, "bw_khz")])
def test_snr_threshold_outside_the_table_is_a_config_error(sf, bw, field):
    with pytest.raises(ConfigError, match=rf"^{field}: \[{sf if field == 'sf' else bw}\] not in the allowed set"):
        physics.snr_threshold_db(sf, bw)


# ------------------------------------------------------------------ hover power
def test_hover_power_of_the_default_parameters_by_hand():
    # profile term: 1.168^-1/2 * 0.045 * 0.214^-1/2 * 0.001195^-3/2 * 0.011 / 8
    #             = 0.925304 * 0.045 * 2.161694 * 24207.3 * 0.001375 = 2.99595
    # induced term: 1.11 / sqrt(2 * 1.168 * 0.214) = 1.11 / 0.707039 = 1.569927
    # P = 4 * 5^1.5 * (2.99595 + 1.569928) = 44.72136 * 4.56588 = 204.19 W
    profile = 1.168**-0.5 * 0.045 * 0.214**-0.5 * 0.001195**-1.5 * 0.011 / 8
    assert profile == pytest.approx(2.99595, abs=1e-4)
    induced = 1.11 / math.sqrt(2 * 1.168 * 0.214)
    assert induced == pytest.approx(1.569927, abs=1e-5)
    assert 4 * 5**1.5 * (profile + induced) == pytest.approx(hand_hover_w(), rel=1e-12)
    assert hand_hover_w() == pytest.approx(204.19, abs=0.01)
    assert physics.hover_power_w(CFG) == pytest.approx(hand_hover_w(), rel=1e-12)
    assert TABLES.hover_w == pytest.approx(hand_hover_w(), rel=1e-12)


def test_hover_power_follows_the_config():
    cfg = CFG.replace(hover={"n_rotors": 6, "weight_n": 30.0})  # W_r = 5 N still: P scales with n
    assert physics.hover_power_w(cfg) == pytest.approx(6 / 4 * hand_hover_w(), rel=1e-12)
    heavier = CFG.replace(hover={"weight_n": 40.0})  # W_r = 10 N: P scales with W_r^1.5
    assert physics.hover_power_w(heavier) == pytest.approx(2**1.5 * hand_hover_w(), rel=1e-12)


# ------------------------------------------------------------------ a hand-built slot
# 2 UAVs, 4 EDs; ED 3 is unassociated (it must neither transmit nor interfere).
#            ED0     ED1     ED2       ED3
GAINS = np.array(
    [
        [1e-9, 2e-14, 1e-11, 5e-9],  # UAV 0
        [3e-11, 1e-12, 3.98e-14, 5e-9],  # UAV 1
    ]
)
SERVING = np.array([0, 0, 1, 0])
ASSOCIATED = np.array([True, True, True, False])
SF_IDX = np.array([0, 2, 0, 0])  # SF 7, 9, 7, 7: ED0 and ED2 share SF 7 (at different UAVs)
TP_IDX = np.array([4, 2, 0, 4])  # 14, 8, 2, 14 dBm
BW_IDX = np.array([0, 0, 1, 0])  # 125, 125, 250, 125 kHz (one BW per UAV, as in per_uav mode)


def hand_slot(interference: str = "paper") -> dict[str, float]:
    p = [dbm(14.0), dbm(8.0), dbm(2.0)]
    w = [125e3, 125e3, 250e3]
    thr = [-7.5, -12.5, -9.0]  # SF7/125, SF9/125, SF7/250
    # SNR at the serving UAV: rho = P G / sigma^2
    snr0 = p[0] * 1e-9 / NOISE_W  # 25118.9 (44.0 dB)
    snr1 = p[1] * 2e-14 / NOISE_W  # 0.12619 (-8.99 dB)
    snr2 = p[2] * 3.98e-14 / NOISE_W  # 0.06308 (-12.0 dB)
    if interference == "paper":
        # Eq. (sinr): ED0 and ED2 share SF 7, each interferes with its SNR at ITS OWN UAV
        sinr = [snr0 / (snr2 + 1), snr1 / (0 + 1), snr2 / (snr0 + 1)]
    else:
        # physical: interferer's power at the victim's serving UAV
        i0 = p[2] * 1e-11 / NOISE_W  # ED2 heard at UAV 0
        i2 = p[0] * 3e-11 / NOISE_W  # ED0 heard at UAV 1
        sinr = [snr0 / (i0 + 1), snr1, snr2 / (i2 + 1)]
    sinr_db = [10 * math.log10(x) for x in sinr]
    rates = [w[i] * math.log2(1 + sinr[i]) for i in range(3)]
    hover = hand_hover_w()
    ee = (rates[0] + rates[1]) / (p[0] + p[1] + hover) + rates[2] / (p[2] + hover)
    decoded = [sinr_db[i] >= thr[i] for i in range(3)]
    xi = sum(decoded) / 4  # over ALL V = 4 EDs
    snr_db = [10 * math.log10(x) for x in (snr0, snr1, snr2)]
    margins = [snr_db[i] - thr[i] for i in range(3)]
    scores = [min(m, 20) / 20 if m >= 0 else max(m / 2, -10) for m in margins]
    beta = sum(scores) / 3
    p_total = sum(p) + 2 * hover
    return {
        "sinr0": sinr[0], "sinr1": sinr[1], "sinr2": sinr[2],
        "ee_sys": ee, "success_rate": xi, "beta": beta, "p_total_w": p_total,
        "rate_sum_bps": sum(rates), "mean_sinr_db": sum(sinr_db) / 3, "n_unassociated": 1.0,
        "reward": 4e-4 * ee + 5.0 * xi + 1.0 * beta - 1e-2 * p_total,
        "decoded": decoded, "margins": margins,
    }  # fmt: skip


def test_hand_slot_is_the_interesting_case():
    h = hand_slot()
    # one decoded, one decoded thanks to no interference, one lost to interference; margins of both signs
    assert h["decoded"] == [True, True, False]
    assert h["margins"][1] > 0 > h["margins"][2]
    assert h["margins"][0] > 20  # the clipped branch


@pytest.mark.parametrize("interference", ["paper", "cross_gain"])
def test_slot_metrics_of_a_hand_built_slot(interference):
    cfg = CFG.replace(interference=interference, n_eds=4)
    got = physics.slot_metrics(GAINS, SERVING, ASSOCIATED, SF_IDX, TP_IDX, BW_IDX, cfg, physics.Tables.from_config(cfg))
    h = hand_slot(interference)
    assert set(got) == set(physics.SLOT_METRICS)
    for key in physics.SLOT_METRICS:
        assert float(got[key]) == pytest.approx(h[key], rel=1e-9), key
    if interference == "paper":
        # pinned: R0 = 125e3 log2(1 + 23628) = 1.816e6, R1 = 125e3 log2(1.126) = 21.4e3, R2 ~ 1 bit/s;
        # EE = 1.8374e6 / (204.19 + 0.0314) + ~0 = 8997 bit/J
        assert h["ee_sys"] == pytest.approx(8997.3, abs=0.5)


def test_sinr_paper_by_hand():
    snr_serving = np.array([dbm(14) * 1e-9, dbm(8) * 2e-14, dbm(2) * 3.98e-14, dbm(14) * 5e-9]) / NOISE_W
    got = physics.sinr_paper(snr_serving, SF_IDX, ASSOCIATED, n_sf=6)
    h = hand_slot("paper")
    np.testing.assert_allclose(got[:3], [h["sinr0"], h["sinr1"], h["sinr2"]], rtol=1e-12)
    assert got[3] == 0.0  # silent ED


def test_sinr_cross_gain_by_hand():
    p_w = np.array([dbm(14), dbm(8), dbm(2), dbm(14)])
    got = physics.sinr_cross_gain(p_w, GAINS, SERVING, SF_IDX, ASSOCIATED, 6, NOISE_W)
    h = hand_slot("cross_gain")
    np.testing.assert_allclose(got[:3], [h["sinr0"], h["sinr1"], h["sinr2"]], rtol=1e-12)
    assert got[3] == 0.0
    # a second hand example: three EDs on one SF, two at the same UAV
    gains = np.array([[1e-10, 2e-10, 5e-12], [4e-12, 1e-12, 3e-10]])
    p = np.array([1e-3, 2e-3, 1e-3])
    serving = np.array([0, 0, 1])
    out = physics.sinr_cross_gain(p, gains, serving, np.zeros(3, dtype=int), np.ones(3, bool), 6, 1e-15)
    # ED0 at UAV0: own 1e-3*1e-10 = 1e-13 W; interference 2e-3*2e-10 + 1e-3*5e-12 = 4.05e-13 W
    s0 = (1e-13 / 1e-15) / (4.05e-13 / 1e-15 + 1)
    # ED1 at UAV0: own 4e-13 W; interference 1e-13 + 5e-15 = 1.05e-13 W
    s1 = (4e-13 / 1e-15) / (1.05e-13 / 1e-15 + 1)
    # ED2 at UAV1: own 3e-13 W; interference 1e-3*4e-12 + 2e-3*1e-12 = 6e-15 W
    s2 = (3e-13 / 1e-15) / (6e-15 / 1e-15 + 1)
    np.testing.assert_allclose(out, [s0, s1, s2], rtol=1e-12)


def test_slot_metrics_broadcast_over_a_batch():
    cfg = CFG.replace(n_eds=4)
    single = physics.slot_metrics(GAINS, SERVING, ASSOCIATED, SF_IDX, TP_IDX, BW_IDX, cfg, TABLES)
    rev = [3, 2, 1, 0]  # the same slot with the EDs listed in reverse order
    stack = lambda a, ax=-1: np.stack([a, np.take(a, rev, axis=ax)])  # noqa: E731
    batch = physics.slot_metrics(
        stack(GAINS), stack(SERVING), stack(ASSOCIATED), stack(SF_IDX), stack(TP_IDX), stack(BW_IDX), cfg, TABLES
    )
    for key in physics.SLOT_METRICS:
        assert batch[key].shape == (2,)
        np.testing.assert_allclose(batch[key], [single[key], single[key]], rtol=1e-12, err_msg=key)


def test_no_ed_associated_gives_finite_neutral_metrics():
    cfg = CFG.replace(n_eds=4)
    got = physics.slot_metrics(GAINS, SERVING, np.zeros(4, bool), SF_IDX, TP_IDX, BW_IDX, cfg, TABLES)
    hover = hand_hover_w()
    assert float(got["ee_sys"]) == 0.0
    assert float(got["success_rate"]) == 0.0
    assert float(got["beta"]) == 0.0
    assert float(got["rate_sum_bps"]) == 0.0
    assert float(got["p_total_w"]) == pytest.approx(2 * hover)
    assert float(got["n_unassociated"]) == 4.0
    assert all(np.isfinite(v).all() for v in got.values())


# ------------------------------------------------------------------ rate, Eq. (shannon) and lora_phy
def test_shannon_rate():
    # R = W log2(1 + SINR): SINR 3 -> 2 bits/s/Hz; SINR 0 -> 0
    thr = np.array([-7.5, -7.5])
    got = physics.rate_bps(np.array([3.0, 0.0]), np.array([125e3, 500e3]), np.array([7, 7]), thr)
    np.testing.assert_allclose(got, [250e3, 0.0])


def test_lora_phy_rate_by_hand():
    # R = SF W / 2^SF * 4 / (4 + CR), delivered only when SINR_dB >= rho_thr(SF, W)
    r_sf7_125 = 7 * 125e3 / 2**7 * 4 / 5  # 5468.75 bit/s
    r_sf12_500 = 12 * 500e3 / 2**12 * 4 / 5  # 1171.875 bit/s
    assert r_sf7_125 == 5468.75 and r_sf12_500 == 1171.875
    sf = np.array([7, 7, 12, 12])
    bw = np.array([125e3, 125e3, 500e3, 500e3])
    thr = np.array([-7.5, -7.5, -25.0, -25.0])
    sinr = 10 ** ((thr + np.array([0.1, -0.1, 0.1, -0.1])) / 10)  # just above / just below
    got = physics.rate_bps(sinr, bw, sf, thr, model="lora_phy", coding_rate=1)
    np.testing.assert_allclose(got, [r_sf7_125, 0.0, r_sf12_500, 0.0])
    cr4 = physics.rate_bps(sinr, bw, sf, thr, model="lora_phy", coding_rate=4)
    np.testing.assert_allclose(cr4, [7 * 125e3 / 128 * 4 / 8, 0.0, 12 * 500e3 / 4096 * 4 / 8, 0.0])


def test_lora_phy_rate_in_a_slot():
    cfg = CFG.replace(rate_model="lora_phy", n_eds=4)
    got = physics.slot_metrics(GAINS, SERVING, ASSOCIATED, SF_IDX, TP_IDX, BW_IDX, cfg, physics.Tables.from_config(cfg))
    # decoded: ED0 (SF7, 125 kHz) and ED1 (SF9, 125 kHz); ED2 is below its threshold -> 0 bit/s
    r0 = 7 * 125e3 / 2**7 * 0.8
    r1 = 9 * 125e3 / 2**9 * 0.8
    hover = hand_hover_w()
    assert float(got["rate_sum_bps"]) == pytest.approx(r0 + r1, rel=1e-12)
    ee = (r0 + r1) / (dbm(14) + dbm(8) + hover) + 0.0 / (dbm(2) + hover)
    assert float(got["ee_sys"]) == pytest.approx(ee, rel=1e-12)


# ------------------------------------------------------------------ beta, reward
@pytest.mark.parametrize(
    "margin,score",
    [(-30.0, -10.0), (-25.0, -10.0), (-4.0, -2.0), (0.0, 0.0), (10.0, 0.5), (20.0, 1.0), (30.0, 1.0)],
)
def test_margin_score(margin, score):
    # min(m, 20) / 20 for m >= 0, max(m / 2, -10) for m < 0
    thr = np.array([-12.5])
    got = physics.margin_score(thr + margin, thr, np.array([True]))
    assert float(got) == pytest.approx(score, abs=1e-12)


def test_margin_score_is_a_mean_over_associated_eds_only():
    thr = np.full(6, -10.0)
    margins = np.array([-30.0, -4.0, 0.0, 10.0, 30.0, -30.0])
    assoc = np.array([True, True, True, True, True, False])  # the last must not count
    got = physics.margin_score(thr + margins, thr, assoc)
    assert float(got) == pytest.approx((-10 - 2 + 0 + 0.5 + 1) / 5, abs=1e-12)
    assert float(physics.margin_score(thr, thr, np.zeros(6, bool))) == 0.0


def test_success_rate_counts_all_eds():
    thr = np.array([-10.0, -10.0, -10.0, -10.0])
    sinr_db = np.array([-9.0, -11.0, 5.0, 5.0])
    assoc = np.array([True, True, True, False])  # the unassociated one is not a success
    assert float(physics.success_rate(sinr_db, thr, assoc)) == 0.5


def test_reward_w4_sign_gives_the_same_penalty():
    ee, xi, beta, p = 1500.0, 0.7, -0.25, 410.0
    hand = 4e-4 * 1500.0 + 5.0 * 0.7 + 1.0 * (-0.25) - 0.01 * 410.0  # 0.6 + 3.5 - 0.25 - 4.1 = -0.25
    assert hand == pytest.approx(-0.25)
    neg = physics.reward(ee, xi, beta, p, RewardWeights(w1=4e-4, w4=-1e-2))
    pos = physics.reward(ee, xi, beta, p, RewardWeights(w1=4e-4, w4=1e-2))
    assert float(neg) == pytest.approx(hand, abs=1e-12)
    assert float(pos) == pytest.approx(hand, abs=1e-12)
    # and end to end through a slot
    m_neg = physics.slot_metrics(GAINS, SERVING, ASSOCIATED, SF_IDX, TP_IDX, BW_IDX, CFG.replace(n_eds=4), TABLES)
    cfg_pos = CFG.replace(n_eds=4, reward={"w4": 1e-2})
    m_pos = physics.slot_metrics(GAINS, SERVING, ASSOCIATED, SF_IDX, TP_IDX, BW_IDX, cfg_pos, TABLES)
    assert float(m_pos["reward"]) == float(m_neg["reward"])
    assert float(m_pos["reward"]) < float(m_pos["success_rate"]) * 5.0 + float(m_pos["beta"]) + 4e-4 * float(
        m_pos["ee_sys"]
    )  # a penalty, not a bonus


def test_reward_weights_are_read_from_the_config():
    cfg = CFG.replace(n_eds=4, reward={"w1": 1e-3, "w2": 2.0, "w3": 0.5, "w4": -0.1})
    m = physics.slot_metrics(GAINS, SERVING, ASSOCIATED, SF_IDX, TP_IDX, BW_IDX, cfg, TABLES)
    h = hand_slot()
    expected = 1e-3 * h["ee_sys"] + 2.0 * h["success_rate"] + 0.5 * h["beta"] - 0.1 * h["p_total_w"]
    assert float(m["reward"]) == pytest.approx(expected, rel=1e-9)


def test_energy_efficiency_by_hand():
    # two UAVs: UAV0 serves ED0 and ED1, UAV1 serves ED2; ED3 silent
    rate = np.array([1000.0, 2000.0, 500.0, 9999.0])
    p = np.array([0.1, 0.2, 0.3, 5.0])
    got = physics.energy_efficiency(rate, p, SERVING, ASSOCIATED, hover_w=10.0, n_uavs=2)
    assert float(got) == pytest.approx(3000.0 / 10.3 + 500.0 / 10.3, rel=1e-12)
    got3 = physics.energy_efficiency(rate, p, SERVING, ASSOCIATED, hover_w=10.0, n_uavs=3)  # an idle UAV adds 0
    assert float(got3) == pytest.approx(float(got), rel=1e-12)
    assert float(physics.total_power_w(p, ASSOCIATED, 10.0, 3)) == pytest.approx(0.6 + 30.0)


def test_tables_from_config():
    # TP set {2, 5, 8, 11, 14} dBm in W, BW set {125, 250, 500} kHz in Hz, noise -120 dBm
    np.testing.assert_allclose(TABLES.tp_w, [10 ** ((p - 30) / 10) for p in (2, 5, 8, 11, 14)], rtol=1e-12)
    np.testing.assert_array_equal(TABLES.bw_hz, [125e3, 250e3, 500e3])
    np.testing.assert_array_equal(TABLES.sf, [7, 8, 9, 10, 11, 12])
    assert TABLES.noise_w == pytest.approx(NOISE_W, rel=1e-12)
    assert TABLES.threshold_db.shape == (6, 3)
    # SNR: rho = P G / sigma^2, e.g. 14 dBm over a 100 dB loss: 0.0251 W * 1e-10 / 1e-15 = 2511.9
    assert float(physics.snr(dbm(14.0), 1e-10, NOISE_W)) == pytest.approx(2511.886, rel=1e-6)


# ------------------------------------------------------------------ faster formulations = the plain formulas
CHANNEL_CFGS = [
    CFG,
    CFG.replace(altitude_m=120.0, carrier_hz=433e6, eta_los_db=1.0, eta_nlos_db=20.0, los_a=9.61, los_b=0.16),
    CFG.replace(eta_los_db=30.0, eta_nlos_db=0.0),  # eta_LoS > eta_NLoS: G not monotone in d_h
]


@pytest.mark.parametrize("cfg", CHANNEL_CFGS)
def test_channel_gain_sq_equals_the_plain_formula(cfg):
    d_h = np.concatenate(
        [[0.0, 1e-6, 1.0, 90.0, 600.0, 1414.2, 5000.0], np.random.default_rng(0).uniform(0, 2000, 1000)]
    )
    g, g_db = physics.channel_gain_sq(d_h * d_h, cfg, with_db=True)
    np.testing.assert_allclose(g, physics.channel_gain(d_h, cfg), rtol=1e-12, atol=0)
    np.testing.assert_allclose(g_db, -physics.path_loss_db(d_h, cfg), rtol=1e-12, atol=0)
    assert np.array_equal(physics.channel_gain_sq(d_h * d_h, cfg), g)  # with or without dB: same G
    # element by element: a value does not depend on the array it is computed in (batch = single)
    assert np.array_equal(physics.channel_gain_sq((d_h * d_h)[3:4], cfg), g[3:4])


def test_gain_decreases_with_distance_flag():
    d2 = np.linspace(0.0, 3000.0, 20001) ** 2
    for cfg in CHANNEL_CFGS:
        g = physics.channel_gain_sq(d2, cfg)
        if physics.gain_decreases_with_distance(cfg):
            assert (np.diff(g) < 0).all()
        else:
            assert (np.diff(g) > 0).any()  # the flag is off exactly where the nearest UAV may not be the best
    assert physics.gain_decreases_with_distance(CFG)
    assert not physics.gain_decreases_with_distance(CHANNEL_CFGS[2])


def test_horizontal_distance_sq_to_is_the_pairwise_entry_bit_for_bit():
    rng = np.random.default_rng(1)
    eds = rng.uniform(0, 1000, (3, 7, 2))
    uav = physics.uav_positions(CFG.replace(n_uavs=4))
    pairs = physics.horizontal_distance_sq(eds, uav)  # [3, 4, 7]
    idx = rng.integers(0, 4, (3, 7))
    got = physics.horizontal_distance_sq_to(eds, uav, idx)
    assert np.array_equal(got, np.take_along_axis(pairs, idx[:, None, :], axis=1)[:, 0])


def test_group_sum_and_lin_to_db_equal_the_plain_forms():
    rng = np.random.default_rng(2)
    values, groups = rng.normal(size=(4, 9)), rng.integers(0, 3, (4, 9))
    want = np.array([[values[i][groups[i] == g].sum() for g in range(3)] for i in range(4)])
    np.testing.assert_allclose(physics.group_sum(values, groups, 3), want, rtol=1e-14, atol=1e-15)
    assert physics.group_sum(values[0], groups[0], 3).shape == (3,)
    x = np.array([0.0, -1.0, 1e-300, 1e-21, 1e-20, 2e-20, 1e-3, 1.0, 123.0, np.inf])
    with np.errstate(divide="ignore"):
        plain = np.maximum(10.0 * np.log10(np.maximum(x, 0.0)), physics.DB_FLOOR)
    assert np.array_equal(physics.lin_to_db(x), plain)
    assert physics.lin_to_db(0.0) == physics.DB_FLOOR and physics.lin_to_db(10.0) == pytest.approx(10.0)


def test_sinr_and_energy_efficiency_by_bincount_equal_the_one_hot_sums():
    rng = np.random.default_rng(3)
    for _ in range(20):
        n, u, v, n_sf = 3, 3, 8, 6
        snr, assoc = rng.uniform(0, 50, (n, v)), rng.random((n, v)) < 0.8
        sf, serving = rng.integers(0, n_sf, (n, v)), rng.integers(0, u, (n, v))
        s_tx = np.where(assoc, snr, 0.0)
        onehot = (sf[..., None] == np.arange(n_sf)) & assoc[..., None]
        same = np.take_along_axis(np.einsum("nvk,nv->nk", onehot, s_tx), sf, axis=-1)
        want = np.where(assoc, s_tx / (np.maximum(same - s_tx, 0.0) + 1.0), 0.0)
        np.testing.assert_allclose(physics.sinr_paper(snr, sf, assoc, n_sf), want, rtol=1e-12)
        rate, p = rng.uniform(0, 1e5, (n, v)), rng.uniform(0, 0.03, (n, v))
        a_uv = (serving[:, None, :] == np.arange(u)[:, None]) & assoc[:, None, :]
        ee = (np.einsum("nuv,nv->nu", a_uv, rate) / (np.einsum("nuv,nv->nu", a_uv, p) + 0.2)).sum(-1)
        np.testing.assert_allclose(physics.energy_efficiency(rate, p, serving, assoc, 0.2, u), ee, rtol=1e-12)


# ---------------------------------------------------------------- allocations shared per UAV
def _shared_vs_generic(n, n_uavs, n_eds, seed, cfg):
    """A random slot with per-UAV allocations, scored by slot_metrics (per-ED allocations
    expanded from the UAVs') and by slot_metrics_shared."""
    rng = np.random.default_rng(seed)
    tables = physics.Tables.from_config(cfg)
    gains = 10.0 ** (-rng.uniform(60.0, 140.0, (n, n_uavs, n_eds)) / 10.0)
    serving = rng.integers(0, n_uavs, (n, n_eds))
    associated = rng.random((n, n_eds)) < rng.choice([0.0, 0.7, 1.0])
    sf_u, tp_u, bw_u = (rng.integers(0, k, (n, n_uavs)) for k in (cfg.n_sf, cfg.n_tp, cfg.n_bw))
    per_ed = [np.take_along_axis(x, serving, axis=-1) for x in (sf_u, tp_u, bw_u)]
    want = physics.slot_metrics(gains, serving, associated, *per_ed, cfg, tables)
    g = physics.at_serving(gains, serving)
    flat = serving + np.arange(n)[:, None] * n_uavs
    counts = physics.group_count(np.where(associated, serving, n_uavs), n_uavs + 1)[:, :-1]
    alloc = physics.shared_allocation(sf_u, tp_u, bw_u, tables)
    got = physics.slot_metrics_shared(g, physics.lin_to_db(g), flat, associated, counts, alloc, cfg, tables)
    return got, want, associated


@pytest.mark.parametrize("seed", range(40))
def test_slot_metrics_shared_equals_slot_metrics(seed):
    """The per-UAV factoring changes the rounding only: random slots (gains over 80 dB, some or
    all EDs silent, every SF/TP/BW), against slot_metrics on the expanded per-ED allocations."""
    rng = np.random.default_rng(1000 + seed)
    n, n_uavs, n_eds = int(rng.integers(1, 5)), int(rng.integers(1, 6)), int(rng.integers(1, 40))
    got, want, associated = _shared_vs_generic(n, n_uavs, n_eds, seed, CFG.replace(n_eds=n_eds, n_uavs=n_uavs))
    assert set(got) == set(physics.SLOT_METRICS)
    for key in physics.SLOT_METRICS:
        assert got[key].shape == (n,)
        assert np.isfinite(got[key]).all(), key
        np.testing.assert_allclose(got[key], want[key], rtol=1e-12, atol=1e-9, err_msg=key)
        if not associated.any():  # nobody transmits: the neutral values of slot_metrics
            assert np.array_equal(got[key], want[key]), key


def test_slot_metrics_shared_refuses_other_models():
    for change in ({"interference": "cross_gain"}, {"rate_model": "lora_phy"}):
        with pytest.raises(ValueError, match="slot_metrics_shared"):
            _shared_vs_generic(1, 2, 4, 0, CFG.replace(n_eds=4, **change))


@pytest.mark.parametrize("rate_model", ["shannon", "lora_phy"])
def test_db_threshold_lin_decides_the_db_comparison_exactly(rate_model):
    """x >= db_threshold_lin(thr) is lin_to_db(x) >= thr for every x: at the rho_thr table (each entry
    and its float neighbours), over a sweep of SINRs around every threshold, and at the floor."""
    cfg = ScenarioConfig(rate_model=rate_model)
    thr = np.concatenate([BatchCore(cfg, 1).tables.threshold_db.ravel(), [-7.5, 0.0, 3.1, physics.DB_FLOOR, -250.0]])
    lin = physics.db_threshold_lin(thr)
    for t, x_thr in zip(thr, lin):
        if t <= physics.DB_FLOOR:
            assert x_thr == -np.inf and physics.lin_to_db(0.0) >= t
            continue
        assert physics.lin_to_db(x_thr) >= t > physics.lin_to_db(np.nextafter(x_thr, 0.0))
        x = 10.0 ** (t / 10.0) * np.linspace(0.999, 1.001, 20_001)
        x = np.concatenate([x, np.nextafter(x, np.inf), [0.0, -1.0, np.inf]])
        assert np.array_equal(x >= x_thr, physics.lin_to_db(x.copy()) >= t)
