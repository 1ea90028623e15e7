"""Fault injection between device and host at scale (firmware_host/linkbench.py)."""

import json

import numpy as np
import pytest

from firmware_host.linkbench import FAULTS, fault_campaign, inject
from model.link import PacketType, encode_packet


@pytest.mark.parametrize("kind", FAULTS)
def test_each_fault_damages_the_packet(kind):
    rng = np.random.default_rng(7)
    pkt = encode_packet(PacketType.FRAME, 1, bytes(range(40)))
    damaged = {inject(rng, pkt, kind)[0] for _ in range(20)}
    assert pkt not in damaged or kind == "insert"  # bytes inserted before the sync word


def test_unknown_fault():
    with pytest.raises(ValueError, match="fault kind must be one of"):
        inject(np.random.default_rng(0), b"xx", "gamma rays")


def test_100k_frames_with_faults():
    """No corrupted frame accepted, every intact frame delivered, every loss counted."""
    r = fault_campaign(100_000, seed=1, fault_rate=0.05)
    assert r["corrupted_accepted"] == 0
    assert r["intact_not_delivered"] == 0
    assert r["lost_counted_by_shot_counter"] == r["frames_lost"] > 0
    assert all(n > 500 for n in r["faults_injected"].values())
    assert r["parser"]["truncated"] > 0 and r["parser"]["bad_crc"] > 0
    assert r["ok"]


def test_bench_link_command(capsys):
    from firmware_host.cli import main

    assert main(["bench", "link", "--json", "--seconds", "0.3", "--gate-len", "32",
                 "--baud", "230400", "--faults", "3000"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert set(res) >= {"decode", "line", "parser_only", "faults"}
    assert res["faults"]["ok"] and res["line"]["baud"] == 230400
    assert res["line"]["packets_rejected"] == 0 and res["decode"]["packets_rejected"] == 0
    # Rates are timed figures on a shared machine: the command must report them, and they must
    # be plausible, but their exact values belong to the benchmark, not to a test.
    assert 0.5 < res["line"]["efficiency"] < 1.5
    assert res["decode"]["frames_per_s"] > 0 and res["line"]["frames_per_s"] > 0
