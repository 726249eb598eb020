"""A machine whose model has no magnet limit, or whose magnet estimate is not to be sent:
``transmit.magnet_limit: null``. TE_Estimates then carries the DBC's "no value" in the magnet
signals (checked by decoding the frame's raw bits with cantools), not another node's
temperature; the hot spot is sent as before. Left out, the key keeps its default."""
from __future__ import annotations

import math
import tempfile
from pathlib import Path

import cantools
from svc_testlib import engine_on_emulator

from thermal_edge.bench.service import _config
from thermal_edge.bus import FrameCodec
from thermal_edge.bus.frames import DEFAULT_DBC_PATH


def _last_estimates(transmit: dict) -> tuple[dict, object]:
    with tempfile.TemporaryDirectory() as tmp:
        cfg = _config(Path(tmp), {"interface": "virtual"}, adapt=False, table4=False, transmit=transmit)
        outs, eng, _ = engine_on_emulator(cfg, "overload", 120.0)
    return outs[-1].estimates_signals(), cfg


def test_a_null_magnet_limit_sends_no_value_in_the_magnet_signals():
    sig, cfg = _last_estimates({"magnet_limit": None})
    assert cfg.transmit.magnet_limit is None
    assert math.isnan(sig["TE_T_Magnet"]) and math.isnan(sig["TE_T_MagnetUpper"])
    assert 20.0 < sig["TE_T_HotSpot"] < 200.0
    data = FrameCodec().encode("TE_Estimates", sig)
    raw = cantools.database.load_file(str(DEFAULT_DBC_PATH)).decode_message("TE_Estimates", data, decode_choices=False,
                                                                          scaling=False)
    assert raw["TE_T_Magnet"] == raw["TE_T_MagnetUpper"] == 4095  # the DBC's NoValueRaw
    assert raw["TE_T_HotSpot"] != 4095


def test_left_out_the_magnet_limit_is_the_default():
    sig, cfg = _last_estimates({"hot_spot_limit": "hot_spot"})
    assert cfg.transmit.magnet_limit == "magnet" and 20.0 < sig["TE_T_Magnet"] < 200.0
