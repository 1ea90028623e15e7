"""hdl.pipeline.Pipeline against the model device: every byte of every FRAME packet.

The ADC stream is the emulator's: shot ``k`` of a ``SceneSource`` (the seed000 survey scene)
starts at clock ``k * prf_clocks`` with its trigger, a line sync every ``LINE_SYNC_SHOTS``
shots; the expected bytes are ``model.device.reference_frames`` wrapped by ``encode_packet`` with
``seq`` counting admitted packets, as ``Device._push_frame`` does. The scene's own bank (K = 8,
L = 64, ``firmware_host.coeffs.scene_bank``) is written through ``coef`` first. Every frame type,
plain and with backpressure on the output; then overload with a small FIFO and a slow
consumer. Two Verilator builds (the production FIFO and the small one).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_hdl_matched_filter import coef_source

from hdl.frame import BYTE, packet_cycles
from hdl.peak_detect import RESULT_LATENCY
from hdl.pipeline import ADC_IN, Pipeline
from hdl.tb.bridge import adc_stream
from hdl.tb.cosim import Design, Sink, Source, cfg_ports, run
from hdl.tb.streams import BACKPRESSURE, PLAIN, Pattern
from model.device import SceneSource, reference_frames
from model.layouts import FrameType
from model.link import PacketType, encode_packet, packet_size
from model.registers import Config

BANK_ID = 3
N_FRAMES = 5


@pytest.fixture(scope="session")
def scene():
    """Source, bank and registers of the seed000 survey scene, as ``albcap demo`` sets them."""
    from firmware_host.coeffs import SURVEY_NOISE_LOG2, scene_bank, survey_scene
    from sim.scene import preset

    sc = survey_scene(preset("seed000"))
    src = SceneSource(sc, seed=5, pool=8)
    sb = scene_bank(sc, n_templates=8, n_taps=64)
    cfg = Config(gate_len=src.n_samples, noise_log2=SURVEY_NOISE_LOG2, out_shift=sb.out_shift,
                 bin_offset=sb.bin_offset, bin_len=sb.bin_len, min_thr=sb.min_thr,
                 bottom_rule=2)
    return src, sb.bank, cfg


def adc_source(src: SceneSource, n: int, prf_clocks: int, pattern: Pattern = PLAIN) -> Source:
    """``n`` shots of the scene as an ADC stream, plus one shot's worth of quiet clocks."""
    return Source(ADC_IN, adc_stream(src, n, prf_clocks), pattern)


def run_pipeline(tmp_path, design, src, bank, cfg, n, prf_clocks, sink: Pattern, label,
                 max_clocks=None, changes=(),
                 watch=("frames_sent", "frames_dropped", "fifo_level", "shots", "frame_idle")):
    """The pipeline on ``n`` shots of the scene; ``changes`` are ``(beat, port, value)`` writes
    made with the ADC stream (``hdl.tb.cosim.Source``)."""
    adc = adc_source(src, n, prf_clocks)
    adc.changes = list(changes)
    static = {**cfg_ports(cfg, "stitch", "cfg_stitch"), **cfg_ports(cfg, "gate", "cfg_gate"),
              **cfg_ports(cfg, "filter", "cfg_filter"), **cfg_ports(cfg, "peak", "cfg_peak"),
              "templates": bank.K, "taps": bank.L, "bank_id": BANK_ID, "acquiring": 1,
              "bank_busy": 0}
    return run(design, tmp_path,
               sources={"coef": coef_source(bank), "i": adc},
               sinks={"o": Sink(BYTE, sink)}, static=static, watch=watch,
               quiet_clocks=prf_clocks + 4 * cfg.gate_len,
               max_clocks=max_clocks or (n + 20) * prf_clocks,
               label=label)


def packets(data: bytes) -> list[bytes]:
    """Split the output at packet boundaries (lengths from the packet headers)."""
    out, at = [], 0
    while at < len(data):
        size = packet_size(int.from_bytes(data[at + 4:at + 6], "little"))
        out.append(data[at:at + size])
        at += size
    return out


def prf_for(ftype: int, gate_len: int) -> int:
    """A trigger period the packetizer keeps up with: its clocks per frame plus a margin."""
    return max(gate_len, packet_cycles(ftype, gate_len)) + RESULT_LATENCY + 64


@pytest.mark.parametrize("sink_name", ["plain", "backpressure"])
@pytest.mark.parametrize("ftype", list(FrameType), ids=[t.name.lower() for t in FrameType])
def test_frames(tmp_path, scene, ftype, sink_name):
    src, bank, cfg = scene
    cfg = cfg.replace(frame_type=ftype)
    prf = prf_for(ftype, cfg.gate_len)
    sink = {"plain": PLAIN, "backpressure": BACKPRESSURE}[sink_name]
    res = run_pipeline(tmp_path, Design(Pipeline), src, bank, cfg, N_FRAMES, prf, sink,
                       f"pipeline-{ftype.name.lower()}-{sink_name}")
    assert not res.timeout and res.violations == {"o": 0}
    data = bytes(res.sinks["o"]["data"].astype(np.uint8).tolist())
    ref = reference_frames(src, cfg, bank, 0, N_FRAMES, prf, bank_id=BANK_ID)
    got = packets(data)
    assert len(got) == N_FRAMES
    for seq, (g, frame) in enumerate(zip(got, ref, strict=True)):
        assert g == encode_packet(PacketType.FRAME, seq, frame), f"packet {seq} differs"
    ends = np.flatnonzero(res.sinks["o"]["last"]) + 1
    assert ends.tolist() == np.cumsum([len(g) for g in got]).tolist()
    assert res.watch == {"frames_sent": N_FRAMES, "frames_dropped": 0, "fifo_level": 0,
                         "shots": N_FRAMES, "frame_idle": 1}
    assert res.sources["i"]["stalls"] == 0, "the ADC input must never wait"
    if ftype == FrameType.PEAKS:
        assert all(f[3] & 0x0C == 0x0C for f in ref), "the scene has a surface and a bottom"


def check_bank_ids(tmp_path, scene, cfg, prf, changes, ids, label):
    """The pipeline on ``len(ids)`` shots of the scene with ``changes`` (``bank_busy`` and
    ``bank_id`` writes): every packet is the model's frame stamped with its ``ids`` entry, in
    order, none dropped, and the pipeline idle at the end."""
    src, bank, _ = scene
    n = len(ids)
    res = run_pipeline(tmp_path, Design(Pipeline), src, bank, cfg, n, prf, PLAIN, label,
                       changes=changes, watch=("frames_sent", "frames_dropped", "frame_idle"))
    assert not res.timeout and res.violations == {"o": 0}
    got = packets(bytes(res.sinks["o"]["data"].astype(np.uint8).tolist()))
    ref = {b: reference_frames(src, cfg, bank, 0, n, prf, bank_id=b) for b in set(ids)}
    want = [ref[b][k] for k, b in enumerate(ids)]
    assert len(got) == n
    for seq, (g, frame) in enumerate(zip(got, want, strict=True)):
        assert g == encode_packet(PacketType.FRAME, seq, frame), f"packet {seq} differs"
    assert res.watch == {"frames_sent": n, "frames_dropped": 0, "frame_idle": 1}


@pytest.mark.parametrize("gate_len", [None, 8, 1], ids=["scene", "gate8", "gate1"])
def test_held_frames_take_the_bank_id_they_enter_with(tmp_path, scene, gate_len):
    """``bank_busy`` holds frames 1 and 2 at the filter's door while the packetizer waits for
    a header; it drops, with a new ``bank_id``, as frame 3 is triggered. A header goes to the
    packetizer only once its frame is inside, so every held frame carries the new id, as the
    frames of a bank committed while they waited use the new bank. (The count of frames
    inside waiting for their headers does not reach two here.)

    With the scene's gate a frame's header comes long after its frame entered; with short
    gates it is waiting when the frame enters and is taken on the next clock, the one step
    where the count goes 0 -> 1 -> 0 on consecutive clocks (and "a header may go" must fall
    again before frame 1's header is complete)."""
    cfg = scene[2].replace(frame_type=FrameType.PEAKS, gate_len=gate_len or scene[2].gate_len)
    prf = prf_for(FrameType.PEAKS, cfg.gate_len)
    assert 3 * cfg.gate_len <= 4096, "the gate's FIFO must hold the held frames"
    # (frame 0 has long passed the hold when the busy rises, a clock before frame 1's trigger)
    changes = [(prf - 1, "bank_busy", 1),
               (3 * prf, "bank_busy", 0), (3 * prf, "bank_id", BANK_ID + 1)]
    check_bank_ids(tmp_path, scene, cfg, prf, changes,
                   [BANK_ID, BANK_ID + 1, BANK_ID + 1, BANK_ID + 1],
                   f"pipeline-bank-busy-{cfg.gate_len}")


@pytest.mark.parametrize("gate_len", [8, 1])
def test_a_header_waits_for_its_frame_after_one_taken_as_its_frame_entered(tmp_path, scene,
                                                                            gate_len):
    """Short gates, a trigger period past the bank's load (512 words, a word a clock).
    ``bank_busy`` holds frame 1 at the filter's door; it drops with a new ``bank_id`` as frame
    2 is triggered and rises again while frame 2's first sample is on its way, so that frame 2
    waits until frame 3's trigger, where it drops with a third id.

    Frame 1's header (frame 0's, with a gate of one sample) is complete and waiting when its
    frame enters, and is taken on the next clock: the count of frames waiting for their
    headers goes 0 -> 1 -> 0 on consecutive clocks. Frame 2's header is complete, and the
    packetizer free, long before frame 2 enters; "a header may go" must be low in between, or
    frame 2 carries the second id where the third is due."""
    cfg = scene[2].replace(frame_type=FrameType.PEAKS, gate_len=gate_len)
    prf = 600
    assert prf > prf_for(FrameType.PEAKS, gate_len) + 8
    # frame 1 passes the hold 4 clocks after the beat of the drop, frame 2's first sample
    # some 19 clocks after its trigger (the trigger -> entry latency of frame 0 here)
    changes = [(prf - 1, "bank_busy", 1),
               (2 * prf, "bank_busy", 0), (2 * prf, "bank_id", BANK_ID + 1),
               (2 * prf + 8, "bank_busy", 1),
               (3 * prf, "bank_busy", 0), (3 * prf, "bank_id", BANK_ID + 2)]
    check_bank_ids(tmp_path, scene, cfg, prf, changes,
                   [BANK_ID, BANK_ID + 1, BANK_ID + 2, BANK_ID + 2],
                   f"pipeline-bank-busy-twice-{gate_len}")


@pytest.mark.parametrize("stop", [200, 500])
def test_frame_idle_is_low_with_a_frame_inside(tmp_path, scene, stop):
    """Runs cut short (``max_clocks``) while the first frame streams into the filter, early
    and late in it: ``frame_idle`` is low (a commit would otherwise change the bank under the
    frame); it is high once everything has left (``test_frames``)."""
    src, bank, cfg = scene
    cfg = cfg.replace(frame_type=FrameType.PEAKS)
    assert stop + 64 < cfg.gate_len, "the cut must fall inside the first frame"
    res = run_pipeline(tmp_path, Design(Pipeline), src, bank, cfg, 2,
                       prf_for(FrameType.PEAKS, cfg.gate_len), PLAIN, f"pipeline-idle-{stop}",
                       max_clocks=stop)
    assert res.timeout
    assert res.watch["frame_idle"] == 0


def test_overload_drops_whole_frames(tmp_path, scene):
    """Slow consumer, triggers faster than the packets leave: the FIFO fills and frames are
    dropped, all whole. (The production build, 32 KiB: stitched packets of 1 512 bytes come
    every 814 clocks and leave at a byte per 3 clocks, so the FIFO is full after some 26
    frames; a build with a small FIFO would cost a Verilator build of its own.)"""
    src, bank, cfg = scene
    cfg = cfg.replace(frame_type=FrameType.STITCHED)
    n, prf = 34, cfg.gate_len + 64
    res = run_pipeline(tmp_path, Design(Pipeline), src, bank, cfg, n, prf,
                       Pattern("periodic", on=1, off=2), "pipeline-overload",
                       max_clocks=400_000)
    assert not res.timeout and res.violations == {"o": 0}
    got = packets(bytes(res.sinks["o"]["data"].astype(np.uint8).tolist()))
    ref = reference_frames(src, cfg, bank, 0, n, prf, bank_id=BANK_ID)
    shots = [int.from_bytes(g[8 + 10:8 + 12], "little") for g in got]
    assert shots == sorted(set(shots)) and n - len(shots) >= 3, shots
    for seq, (g, s) in enumerate(zip(got, shots, strict=True)):
        assert g == encode_packet(PacketType.FRAME, seq, ref[s]), f"shot {s} differs"
    w = res.watch
    assert w["frames_sent"] == len(got)
    assert w["frames_sent"] + w["frames_dropped"] == w["shots"] == n
    assert w["fifo_level"] == 0 and w["frame_idle"] == 1
    assert res.sources["i"]["stalls"] == 0


def test_register_slice_sustains_one_transfer_per_clock():
    """The slices between the stages must not halve the rate (a depth-2 SyncFIFOBuffered
    does: its 1-entry inner FIFO refuses a write on the clock its entry moves out)."""
    from amaranth.sim import Simulator

    from hdl.pipeline import register_slice

    dut = register_slice(8)
    moved = {"w": 0, "r": 0}

    async def drive(ctx):
        ctx.set(dut.w_en, 1)
        ctx.set(dut.r_en, 1)
        for i in range(60):
            ctx.set(dut.w_data, i)
            await ctx.tick()

    async def count(ctx):
        async for _clk, _rst, w_rdy, r_rdy in ctx.tick().sample(dut.w_rdy, dut.r_rdy):
            moved["w"] += int(w_rdy)
            moved["r"] += int(r_rdy)

    sim = Simulator(dut)
    sim.add_clock(1e-6)
    sim.add_testbench(drive)
    sim.add_process(count)
    sim.run_until(60e-6)
    assert moved["w"] >= 58 and moved["r"] >= 56, moved


@pytest.mark.parametrize("p_write, p_read", [(1.0, 1.0), (0.5, 1.0), (1.0, 0.3), (0.6, 0.6)])
def test_register_slice_keeps_order_and_loses_nothing(p_write, p_read):
    """Every word written comes out once, in order, under idle insertion and backpressure;
    ``w_rdy`` is low only while both entries are full (the output held and the skid in use)."""
    from amaranth.sim import Simulator

    from hdl.pipeline import register_slice

    dut = register_slice(8)
    rng = np.random.default_rng(int(100 * p_write + 10 * p_read))
    wants_w, wants_r = rng.random(400) < p_write, rng.random(400) < p_read
    written, read, held = [], [], []

    async def bench(ctx):
        nxt = 0
        for t in range(400):
            ctx.set(dut.w_data, nxt & 0xFF)
            ctx.set(dut.w_en, int(wants_w[t]))
            ctx.set(dut.r_en, int(wants_r[t]))
            w_rdy, r_rdy = ctx.get(dut.w_rdy), ctx.get(dut.r_rdy)
            if wants_w[t] and w_rdy:
                written.append(nxt & 0xFF)
                nxt += 1
            if wants_r[t] and r_rdy:
                read.append(ctx.get(dut.r_data))
            held.append(len(written) - len(read))
            if not w_rdy:
                # refused only when full: the output and the skid both hold an entry
                assert len(written) - len(read) + (1 if wants_r[t] and r_rdy else 0) == 2
            await ctx.tick()

    sim = Simulator(dut)
    sim.add_clock(1e-6)
    sim.add_testbench(bench)
    sim.run()
    assert read == written[:len(read)] and len(written) - len(read) <= 2
    assert max(held) <= 2 and len(read) > 50


@pytest.mark.parametrize("capacity, latency, write_delay",
                         [(7, 6, 1), (16, 15, 2), (3, 1, 0), (5, 5, 4), (1, 3, 2)])
def test_beside_ring_pairs_every_sample(capacity, latency, write_delay):
    """``_Beside`` beside a stand-in stage that holds at most ``capacity`` samples and lets
    each leave ``latency`` clocks after it entered at the soonest, in order, its output taken
    at random (4 000 clocks, random input gaps): the ring shows each sample's entry on the
    clock it leaves, also when the stage is full and when samples leave at their soonest."""
    from amaranth.hdl import Module
    from amaranth.sim import Simulator

    from hdl.pipeline import _Beside

    top = Module()
    ring = top.submodules.ring = _Beside(12, capacity, latency, write_delay)
    rng = np.random.default_rng(capacity * 100 + latency)
    n = 4000
    p_in = np.repeat(rng.choice([0.3, 0.7, 1.0], n // 200), 200)
    p_out = np.repeat(rng.choice([0.2, 0.6, 1.0], n // 200), 200)
    seen = {"full": 0, "soonest": 0, "left": 0}

    async def bench(ctx):
        inside = []  # (data, clock entered), oldest first
        for t in range(n):
            leaves = bool(inside) and t - inside[0][1] >= latency and rng.random() < p_out[t]
            if leaves:
                data, entered = inside.pop(0)
                assert ctx.get(ring.r_data) == data, (t, entered)
                seen["soonest"] += t - entered == latency
                seen["left"] += 1
            ctx.set(ring.r_en, int(leaves))
            enters = len(inside) < capacity and rng.random() < p_in[t]
            seen["full"] += len(inside) == capacity
            if enters:
                inside.append((int(rng.integers(0, 1 << 12)), t))
                ctx.set(ring.w_data, inside[-1][0])
            ctx.set(ring.w_en, int(enters))
            await ctx.tick()

    sim = Simulator(top)
    sim.add_clock(1e-6)
    sim.add_testbench(bench)
    sim.run()
    assert seen["left"] > 500 and seen["full"] > 50 and seen["soonest"] > 50


def test_beside_ring_refuses_a_write_later_than_the_stage():
    from hdl.pipeline import _Beside

    with pytest.raises(ValueError, match=r"^write_delay must be an integer in \[0, latency = "
                                         r"6\), not 6: the entry would not be there"):
        _Beside(8, 7, 6, write_delay=6)
    with pytest.raises(ValueError, match=r"^capacity must be an integer >= 1, not 0$"):
        _Beside(8, 0, 6)


def test_register_slice_width_error():
    from hdl.pipeline import RegisterSlice

    with pytest.raises(ValueError, match=r"^width must be an integer >= 1, not 0$"):
        RegisterSlice(0)
