"""The LoRa link: SNR thresholds (Table snr_threshold), SNR, SINR (Eq. sinr) with the paper's
or the cross-gain interference, and the bit rate (Eq. shannon, or the LoRa PHY rate)."""

from __future__ import annotations

from typing import Literal

import numpy as np

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.physics.arrays import group_index, lin_to_db
from uavlora_rllib.sim.scenario import SNR_THRESHOLD_TABLE_DB


# ---------------------------------------------------------------- LoRa thresholds, Table (snr_threshold)
def snr_threshold_db(sf: np.ndarray | int, bw_khz: np.ndarray | int) -> np.ndarray:
    """rho_thr(SF, BW) in dB from the paper's table; raises ConfigError outside the table."""
    sf_a = np.asarray(sf)
    bw_a = np.asarray(bw_khz)
    sfs = np.array(sorted(SNR_THRESHOLD_TABLE_DB))
    bws = np.array([125, 250, 500])
    bad_sf = ~np.isin(sf_a, sfs)
    bad_bw = ~np.isin(bw_a, bws)
    if bad_sf.any():
        raise ConfigError(f"sf: {np.unique(sf_a[bad_sf]).tolist()} not in the allowed set {sfs.tolist()}")
    if bad_bw.any():
        raise ConfigError(f"bw_khz: {np.unique(bw_a[bad_bw]).tolist()} not in the allowed set {bws.tolist()}")
    table = np.array([[SNR_THRESHOLD_TABLE_DB[s][b] for b in bws] for s in sfs])
    return table[np.searchsorted(sfs, sf_a), np.searchsorted(bws, bw_a)]


# ---------------------------------------------------------------- SNR, SINR (Eq. sinr), rate (Eq. shannon)
def snr(tx_power_w: np.ndarray, gain: np.ndarray, noise_w: float) -> np.ndarray:
    """rho = P G / sigma^2 (linear)."""
    return tx_power_w * gain / noise_w


def _same_sf_onehot(sf_idx: np.ndarray, associated: np.ndarray, n_sf: int) -> np.ndarray:
    """[..., V, n_sf] one-hot of each transmitting ED's SF (zero rows for silent EDs)."""
    return (sf_idx[..., None] == np.arange(n_sf)) & associated[..., None]


def sinr_paper_tx(s_tx: np.ndarray, sf_idx: np.ndarray, n_sf: int, out: np.ndarray | None = None) -> np.ndarray:
    """Eq. (sinr) given s_tx = the SNR of each ED, 0 for silent EDs (see `sinr_paper`);
    `out`: a C-contiguous array of the broadcast shape to write the result into."""
    shape = s_tx.shape if s_tx.shape == sf_idx.shape else np.broadcast_shapes(s_tx.shape, sf_idx.shape)
    idx = group_index(sf_idx, n_sf, shape)
    s_flat = s_tx.reshape(-1) if s_tx.shape == shape else np.broadcast_to(s_tx, shape).reshape(-1)
    n_bins = (idx.size // shape[-1]) * n_sf if idx.size else 0
    if out is not None:
        sinr_of_groups(s_flat, idx, n_bins, out=out.reshape(-1))
        return out
    return sinr_of_groups(s_flat, idx, n_bins).reshape(shape)


def sinr_of_groups(s_flat: np.ndarray, group: np.ndarray, n_bins: int, out: np.ndarray | None = None) -> np.ndarray:
    """Eq. (sinr) of EDs whose interferers are the EDs of the same group (flat bin per ED:
    scenario and SF): s / (sum of the group's s - s + 1), s_flat and group 1-D."""
    total: np.ndarray = np.bincount(group, weights=s_flat, minlength=n_bins)  # (float: weighted)
    interference = total.take(group)  # sum over the ED's own SF, itself included
    interference -= s_flat  # >= 0 exactly: a running sum of terms >= 0 never falls below one of them
    interference += 1.0
    return np.divide(s_flat, interference, out=interference if out is None else out)


def sinr_paper(snr_serving: np.ndarray, sf_idx: np.ndarray, associated: np.ndarray, n_sf: int) -> np.ndarray:
    """Eq. (sinr): SINR_v = rho_v / (sum_{v' != v, same SF, associated} rho_{a_v', v'} + 1).

    The interference of v' is its SNR at ITS OWN serving UAV, as the paper writes it.
    Silent (unassociated) EDs neither transmit nor interfere; their SINR is 0.
    """
    return sinr_paper_tx(np.where(associated, snr_serving, 0.0), np.asarray(sf_idx), n_sf)


def sinr_cross_gain(
    tx_power_w: np.ndarray,
    gains: np.ndarray,
    serving_uav: np.ndarray,
    sf_idx: np.ndarray,
    associated: np.ndarray,
    n_sf: int,
    noise_w: float,
) -> np.ndarray:
    """Physical variant: interference at v's serving UAV u is sum_{v'} P_v' G_{u,v'} / sigma^2.

    tx_power_w, serving_uav, sf_idx, associated: [..., V]; gains: [..., U, V]. The leading
    axes broadcast against each other (the baselines score candidate actions [C, N, V] against
    the batch's gains [N, U, V] and association [N, V]); the index arrays are broadcast to the
    common shape because take_along_axis needs as many axes in its indices as in its array.
    """
    tx_power_w, sf_idx = np.asarray(tx_power_w), np.asarray(sf_idx)
    associated, serving_uav = np.asarray(associated), np.asarray(serving_uav)
    lead = np.broadcast_shapes(
        tx_power_w.shape, sf_idx.shape, associated.shape, serving_uav.shape, gains.shape[:-2] + gains.shape[-1:]
    )
    sf_idx, associated, serving_uav = (np.broadcast_to(x, lead) for x in (sf_idx, associated, serving_uav))
    onehot = _same_sf_onehot(sf_idx, associated, n_sf)
    p_tx = np.where(associated, tx_power_w, 0.0)
    rx = gains * p_tx[..., None, :]  # [..., U, V] power each UAV receives from each ED
    per_uav_sf = np.einsum("...uv,...vn->...un", rx, onehot)  # [..., U, n_sf]
    u = serving_uav[..., None, :]
    own = np.take_along_axis(rx, u, axis=-2)[..., 0, :]  # [..., V]
    at_serving = np.take_along_axis(per_uav_sf, serving_uav[..., :, None], axis=-2)  # [..., V, n_sf]
    same = np.take_along_axis(at_serving, sf_idx[..., None], axis=-1)[..., 0]
    interference = np.maximum(same - own, 0.0) / noise_w
    return np.where(associated, (own / noise_w) / (interference + 1.0), 0.0)


def lora_phy_bit_rate(sf: np.ndarray, bw_hz: np.ndarray, coding_rate: int) -> np.ndarray:
    """The LoRa PHY bit rate of a decoded frame, SF W / 2^SF * 4 / (4 + CR) [bit/s] (docs/model.md#rate)."""
    return sf * bw_hz / np.power(2.0, sf) * 4.0 / (4.0 + coding_rate)


def rate_bps(
    sinr: np.ndarray,
    bw_hz: np.ndarray,
    sf: np.ndarray | None,
    threshold_db: np.ndarray,
    model: Literal["shannon", "lora_phy"] = "shannon",
    coding_rate: int = 1,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Eq. (shannon): R = W log2(1 + SINR), or the LoRa PHY bit rate (extension, docs/model.md#rate):
    R = SF W / 2^SF * 4 / (4 + CR), delivered only when SINR_dB >= rho_thr(SF, W).
    `out`: an array of the result's shape for the Shannon rate to be written into."""
    if model == "shannon":
        if out is None:
            return bw_hz * np.log2(np.add(sinr, 1.0))
        np.add(sinr, 1.0, out=out)
        np.log2(out, out=out)
        return np.multiply(bw_hz, out, out=out)
    assert sf is not None, "rate_bps: the LoRa PHY rate needs sf"
    r = np.where(lin_to_db(sinr) >= threshold_db, lora_phy_bit_rate(sf, bw_hz, coding_rate), 0.0)
    if out is not None:
        out[...] = r
        return out
    return r
