"""hdl.synth: Yosys and nextpnr-ecp5 (YoWASP) on a real component; figures parsed."""

import json

import pytest

from firmware_host.cli import main
from hdl.synth import (
    DEVICE,
    MAPPINGS,
    PIPELINE_STAGES,
    SPEEDS,
    _yosys_script,
    failing_endpoints,
    figure_key,
    fmax_by_stage,
    missing_by_depth,
    missing_on,
    near_by_port,
    near_clock,
    print_table,
    record_figures,
    stage_summary,
    synth_all,
    synthesize,
)


class TestSynth:
    def test_stitch_figures(self, tmp_path, capsys):
        r = synthesize("albcap_stitch", work_dir=tmp_path)
        # the gain-ratio multiplier maps onto one ECP5 DSP block; the rest is a few LUTs
        assert r["dsps"] == 1 and r["brams"] == 0
        assert 50 < r["luts"] < 2000 and 20 < r["ffs"] < 2000
        assert 40 < r["fmax_mhz"] < 600
        assert abs(r["samples_per_s"] - r["fmax_mhz"] * 1e6) < 1e5  # one lane
        assert (tmp_path / "report.json").exists() and (tmp_path / "albcap_stitch.v").exists()
        assert r["router"] == "router1" and r["placer"] == "heap"
        # by default the netlist placed is Yosys's with its cones of at most four sources one
        # LUT4 deep, proven equal to it
        assert r["remap"]["max_inputs"] == 4 and r["remap"]["proven_equal"], r["remap"]
        assert "Max frequency" in (tmp_path / "nextpnr.log").read_text()
        # the path that holds fmax: its delay is the clock period fmax gives
        w = r["worst_path"]
        assert w["from"] and w["to"] and "TRELLIS" not in w["from"] + w["to"], w
        assert 0 < w["routing_ns"] < w["ns"] and w["logic_steps"] >= 1
        assert 1000 / w["ns"] == pytest.approx(r["fmax_mhz"], rel=0.05)
        # every endpoint's arrival: against a clock 0.3 ns short of the worst path, the worst
        # register is the path's end, at nextpnr's own -0.3 ns; against one just longer,
        # nothing fails
        report = json.loads((tmp_path / "report.json").read_text())
        short = failing_endpoints(report, w["ns"] - 0.3)
        assert short["worst"][0]["slack_ns"] == pytest.approx(-0.3, abs=0.01), short
        assert short["worst"][0]["register"] == w["to"]
        assert short["endpoints"] >= short["registers"] >= 1
        assert failing_endpoints(report, w["ns"] + 0.01)["endpoints"] == 0
        assert r["failing"] == failing_endpoints(report, 1000 / r["target_mhz"])
        assert r["near"] == near_clock(report, 1000 / r["target_mhz"])
        # every timed endpoint of a real report by its input: with no margin to spare, all
        every = near_by_port(report, 0.0, margin=0.0)
        assert every["endpoints"] == sum(every["ports"].values()) > r["ffs"] // 2
        assert {"DI", "CE"} <= set(every["ports"]) and every["shared"]
        print_table({"device": DEVICE, "components": {"albcap_stitch": r}})
        table = capsys.readouterr().out
        assert f"worst path {w['from']} -> {w['to']}: {w['ns']} ns" in table
        assert table.split("\n")[2].split()[:2] == ["stitch", "out"]

    def test_command_json(self, capsys, tmp_path):
        out = tmp_path / "fpga.json"
        # router2 and the static placer here, so that the options reach nextpnr (router1 and
        # heap run in the test above)
        assert main(["hdl", "synth", "--json", "--component", "albcap_stitch",
                     "--router", "router2", "--placer", "static", "--seed", "7",
                     "--remap", "6", "--out", str(out)]) == 0
        res = json.loads(capsys.readouterr().out)
        assert json.loads(out.read_text())["figures"]["albcap_stitch"]["fmax_mhz"] == \
            res["components"]["albcap_stitch"]["fmax_mhz"]
        assert res["device"]["part"] == "LFE5U-85F"
        assert set(res["components"]) == {"albcap_stitch"}
        assert res["components"]["albcap_stitch"]["router"] == "router2"
        assert res["components"]["albcap_stitch"]["placer"] == "static"
        assert res["components"]["albcap_stitch"]["seed"] == 7
        # the netlist placed: Yosys's with its small cones one LUT deep, proven equal to it
        remap = res["components"]["albcap_stitch"]["remap"]
        assert remap["max_inputs"] == 6 and remap["proven_equal"], remap
        assert {"fmax_mhz", "luts", "ffs", "dsps", "brams", "samples_per_s"} <= set(
            res["components"]["albcap_stitch"])

    def test_several_seeds_keep_the_lowest(self, capsys, tmp_path):
        """``--seed 1 2``: each seed placed, the lowest kept, every seed's fmax recorded; with
        ``--work-dir`` each seed's nextpnr files kept."""
        assert main(["hdl", "synth", "--json", "--component", "albcap_stitch",
                     "--seed", "1", "2", "--work-dir", str(tmp_path / "w")]) == 0
        r = json.loads(capsys.readouterr().out)["components"]["albcap_stitch"]
        near = []
        for seed in (1, 2):
            report = json.loads((tmp_path / "w" / "albcap_stitch" / f"seed{seed}" /
                                 "report.json").read_text())
            assert round(min(v["achieved"] for v in report["fmax"].values()), 1) == \
                r["seeds"][str(seed)]
            near.append(near_clock(report, 1000 / r["target_mhz"]))
        # the tail of the arrivals, the lowest seed's and the mean over both
        assert r["near"] == near[[1, 2].index(r["seed"])]
        assert r["near_mean"] == {m: round((near[0][m] + near[1][m]) / 2, 1) for m in near[0]}
        assert set(r["seeds"]) == {"1", "2"}
        assert r["fmax_mhz"] == min(r["seeds"].values()) == r["seeds"][str(r["seed"])]
        assert r["seeds_mean_mhz"] == round(sum(r["seeds"].values()) / 2, 1)
        print_table({"device": DEVICE, "components": {"albcap_stitch": r}})
        out = capsys.readouterr().out
        assert f"the lowest, seed {r['seed']}, shown" in out
        assert f"(mean {r['seeds_mean_mhz']})" in out
        assert "registers within 0.25 / 0.5 / 0.75 ns of the clock: " + " / ".join(
            str(v) for v in r["near"].values()) + " (mean over the seeds " in out
        for bad in ([], [1, 1]):
            with pytest.raises(ValueError, match=r"seeds must be one or more distinct"):
                synth_all(["albcap_stitch"], seed=bad)

    def test_missing_on_several_seeds(self, tmp_path, capsys):
        """``missing_on``: the registers that miss the clock on more than one seed, and on how
        many, and ``missing_any``, how many miss on at least one, checked against each seed's
        own report (kept by ``work_dir``). At 400 MHz the stitch misses at many registers on
        both seeds, on some at one of them only."""
        res = synth_all(["albcap_stitch"], target_mhz=400.0, seed=[1, 2], work_dir=tmp_path)
        r = res["components"]["albcap_stitch"]
        kept = tmp_path / "albcap_stitch"
        assert (kept / "albcap_stitch.v").exists() and (kept / "albcap_stitch.json").exists()
        every = []
        for seed in (1, 2):
            assert "Max frequency" in (kept / f"seed{seed}" / "nextpnr.log").read_text()
            report = json.loads((kept / f"seed{seed}" / "report.json").read_text())
            listed = failing_endpoints(report, 2.5, worst=None)["worst"]
            every.append({x["register"] for x in listed})
        both = sorted(every[0] & every[1])
        assert both and every[0] != every[1]  # (else the test would not tell the two apart)
        assert r["missing_on"] == [{"register": x, "seeds": 2} for x in both][:16]
        assert r["missing_any"] == len(every[0] | every[1]) > len(both)
        # the same misses by the depth of the register, every missing register counted once
        by_depth = r["missing_by_depth"]
        assert sum(x["missing_any"] for x in by_depth) == r["missing_any"]
        assert sum(x["per_seed"] for x in by_depth) == pytest.approx(
            (len(every[0]) + len(every[1])) / 2, abs=0.05 * len(by_depth))
        named = [x for x in by_depth if x["levels"] is not None]
        assert named and [x["levels"] for x in named] == sorted(x["levels"] for x in named)
        assert all(x["missing_any"] <= x["registers"] for x in named)
        print_table(res)
        out = capsys.readouterr().out
        assert "by logic levels, registers missing: " in out
        assert "missing on more than one of the 2 seeds: " in out
        assert f"{r['missing_any']} registers miss the clock on at least one of the 2 seeds" in out
        # counted over placements, the most first, then by name; one placement's alone left out
        assert missing_on([{"a", "b"}, {"b", "c"}, {"b", "c", "d"}]) == [
            {"register": "b", "seeds": 3}, {"register": "c", "seeds": 2}]
        assert missing_on([{"a"}, {"b"}]) == []
        assert missing_on([set("abc"), set("abc")], listed=2) == [
            {"register": "a", "seeds": 2}, {"register": "b", "seeds": 2}]

    def test_stitch_in_context(self, tmp_path):
        """In a shell of registers, placed in context: the clock on a global network (a
        ``DCCA``), the streams through the shell, the static registers on pins of their own."""
        r = synthesize("albcap_stitch", work_dir=tmp_path, context="in", placer="static")
        assert r["context"] == "in" and r["dsps"] == 1 and 40 < r["fmax_mhz"] < 600
        log = (tmp_path / "nextpnr.log").read_text()
        assert "promoting clock net" in log and "routing clock net" in log
        assert "Running Static placer" in log and r["placer"] == "static"
        v = (tmp_path / "albcap_stitch.v").read_text()
        head = v[v.index("module albcap_stitch("):].split(";")[0]
        assert "din" in head and "dout" in head and "cfg__sat_threshold" in head
        assert "i__payload" not in head  # a stream: through the shell's registers
        with pytest.raises(ValueError, match=r"context must be one of \('out', 'in'\), not 'x'"):
            synthesize("albcap_stitch", context="x")

    def test_shell_sorts_the_pipelines_ports(self):
        """The pipeline's single control and status signals (``bank_busy``, ``frame_idle``,
        the counters) go through the shell, timed; only the register groups and the bank's
        shape stay on pins. (``frame_idle``, an output, was once taken for a static input and
        driven twice.)"""
        from amaranth.back import verilog

        from hdl.pipeline import Pipeline
        from hdl.synth import PortShell

        shell = PortShell(Pipeline())
        names = {s.name.split("__")[0] for s in shell.static}
        assert names == {"cfg_stitch", "cfg_gate", "cfg_filter", "cfg_peak", "templates",
                         "taps", "bank_id"}
        text = verilog.convert(shell, name="p", emit_src=False,
                               ports=[shell.domain.clk, shell.din, shell.dout, *shell.static])
        head = text[text.index("module p("):].split(";")[0]
        assert "bank_busy" not in head and "frame_idle" not in head and "din" in head

    def test_shell_times_the_links_register_outputs(self):
        """The link drives the register groups and the bank's shape (outputs named as the
        pipeline's static inputs): the shell times them through its output registers, never
        drives them (it once did, and the link could not be placed in context)."""
        from amaranth.back import verilog

        from hdl.device import Link
        from hdl.synth import PortShell

        shell = PortShell(Link())
        assert shell.static == []
        text = verilog.convert(shell, name="l", emit_src=False, ports=shell.ports)
        head = text[text.index("module l("):].split(";")[0]
        assert "cfg_" not in head and "taps" not in head and "din" in head

    def test_shell_static_registers(self):
        """``static="registers"``: the register groups come from a chain of registers fed by
        ``cfg_din`` (timed, as the link's registers in the device), not from pins."""
        from amaranth.sim import Simulator

        from hdl.stitch import Stitch
        from hdl.synth import PortShell

        core = Stitch()
        shell = PortShell(core, static="registers")
        assert shell.ports == [shell.domain.clk, shell.din, shell.dout, shell.cfg_din]
        pins = PortShell(Stitch())
        assert len(pins.ports) == 3 + len(pins.static)
        pins._MustUse__silence = pins.core._MustUse__silence = True  # (not elaborated)
        bits = sum(len(pin) for pin in shell.static)
        rng = __import__("random").Random(5)
        want = [rng.randrange(2) for _ in range(bits)]
        sim = Simulator(shell)
        sim.add_clock(1e-8)

        async def bench(ctx):
            for b in reversed(want):  # the first bit in travels furthest down the chain
                ctx.set(shell.cfg_din, b)
                await ctx.tick()
            got = []
            for _, port in shell._pinned:
                v = ctx.get(port)
                got += [(v >> i) & 1 for i in range(len(port))]
            assert got == want

        sim.add_testbench(bench)
        sim.run()
        with pytest.raises(ValueError, match=r"static must be one of \('pins', 'registers'\), "
                                             r"not 'wires'"):
            PortShell(Stitch(), static="wires")
        with pytest.raises(ValueError, match=r"static='registers' applies in context only"):
            synthesize("albcap_stitch", static="registers")

    def test_unknown_component(self):
        with pytest.raises(ValueError, match="unknown component 'albcap_fft'"):
            synthesize("albcap_fft")

    def test_unknown_router(self):
        with pytest.raises(ValueError, match="router must be one of .*, not 'router3'"):
            synthesize("albcap_stitch", router="router3")

    def test_bad_seed(self):
        with pytest.raises(ValueError, match=r"seed must be an integer in 1\.\.2\*\*31-1, not 0"):
            synthesize("albcap_stitch", seed=0)

    def test_unknown_placer(self):
        with pytest.raises(ValueError, match=r"placer must be one of \('heap', 'static'\), "
                                             r"not 'sa'"):
            synthesize("albcap_stitch", placer="sa")

    def test_param_errors(self, capsys):
        for args, msg in ((["--param", "lanes"], "--param wants NAME=VALUE"),
                          (["--param", "lanes=four"], "the value must be an integer, not 'four'"),
                          (["--param", "lanes=4"], "--param needs exactly one --component"),
                          (["--static", "registers"],
                           "--static applies in context only: give --context in")):
            with pytest.raises(SystemExit, match=msg):
                main(["hdl", "synth", *args])


def test_missing_by_depth_counts_each_register_at_its_depth():
    depth = {"a": 0, "b": 1, "c": 1, "d": 3}
    missed = [{"b", "d", "$x"}, {"d"}, {"b", "c", "d"}]
    assert missing_by_depth(depth, missed) == [
        {"levels": 0, "registers": 1, "missing_any": 0, "per_seed": 0.0},
        {"levels": 1, "registers": 2, "missing_any": 2, "per_seed": 1.0},
        {"levels": 3, "registers": 1, "missing_any": 1, "per_seed": 1.0},
        {"levels": None, "missing_any": 1, "per_seed": 0.3},
    ]
    assert missing_by_depth(depth, [set(), set()])[1]["missing_any"] == 0
    assert missing_by_depth({}, missed) == []  # one placement's run: no depths taken


def test_failing_endpoints_counts_each_endpoint_once():
    """An endpoint reached from two launches counts once, at its latest arrival; a
    register's bits are one register; a path from or to a pin does not count; a report without
    detailed timing gives None."""
    def ep(cell, port, delay):
        return {"cell": cell, "port": port, "delay": delay, "event": "posedge clk"}
    report = {"detailed_net_timings": [
        {"net": "a", "endpoints": [ep("core.x_TRELLIS_FF_Q", "DI", [4.0, 5.5]),
                                   ep("core.y_TRELLIS_FF_Q_3", "DI", [1.0, 5.2])]},
        {"net": "b", "endpoints": [ep("core.x_TRELLIS_FF_Q", "DI", [4.0, 5.1]),
                                   ep("core.y_TRELLIS_FF_Q_4", "CE", [1.0, 5.3]),
                                   ep("core.z_TRELLIS_FF_Q", "DI", [1.0, 4.9])]},
        # from a pin, unconstrained: not timed against the clock
        {"net": "pin", "event": "<async>",
         "endpoints": [ep("cfg_x_TRELLIS_FF_Q", "M", [6.6, 6.6])]},
        # to a pin, likewise
        {"net": "out", "event": "posedge clk",
         "endpoints": [{**ep("dout$tr_io", "I", [5.9, 5.9]), "event": "<async>"}]}]}
    f = failing_endpoints(report, 5.0)
    assert f["endpoints"] == 3 and f["registers"] == 2
    assert f["worst"] == [{"register": "core.x", "slack_ns": -0.5, "endpoints": 1},
                          {"register": "core.y", "slack_ns": -0.3, "endpoints": 2}]
    assert failing_endpoints(report, 5.0, worst=1)["worst"] == f["worst"][:1]
    assert failing_endpoints({"critical_paths": []}, 5.0) is None


def test_near_clock_counts_each_register_once_by_its_latest_arrival():
    """Registers within each margin of the period, each at its latest endpoint (its bits one
    register), those that miss among them, one at the margin itself not; pins left out; None
    without detailed timing."""
    report = _report(("core.x_TRELLIS_FF_Q", "DI", 5.5), ("core.y_TRELLIS_FF_Q_3", "DI", 4.6),
                     ("core.y_TRELLIS_FF_Q_4", "CE", 4.8), ("core.z_TRELLIS_FF_Q", "DI", 4.6),
                     ("core.w_TRELLIS_FF_Q", "DI", 4.25), ("core.v_TRELLIS_FF_Q", "DI", 3.0),
                     ("cfg_x_TRELLIS_FF_Q", "M", 6.6, "async"))
    assert near_clock(report, 5.0) == {"0.25": 2, "0.5": 3, "0.75": 3}
    assert near_clock(report, 5.0, margins=(0, 1, 2.5)) == {"0": 1, "1": 4, "2.5": 5}
    assert near_clock({"critical_paths": []}, 5.0) is None


def _report(*endpoints):
    """A nextpnr report of one net per endpoint ``(cell, port, arrival_ns[, async])``."""
    return {"detailed_net_timings": [
        {"driver": "d", "port": "Q", "net": f"n{i}",
         "event": "<async>" if a[3:] else "posedge clk",
         "endpoints": [{"cell": a[0], "port": a[1], "delay": [0.5, a[2]],
                        "event": "posedge clk"}]} for i, a in enumerate(endpoints)]}


def test_near_by_port_counts_endpoints_by_input_and_lists_the_shared_nets():
    """Endpoints within the margin by port (bit numbers dropped, each endpoint at its latest
    net), the one at the margin itself not; the nets of the shared inputs (clock enable,
    set/reset, LUT-RAM write address and enable) most endpoints first, ties by name, as many
    as ``listed``; pins left out; None without detailed timing."""
    def net(name, *eps, event="posedge clk"):
        return {"driver": "d", "port": "Q", "net": name, "event": event,
                "endpoints": [{"cell": c, "port": p, "delay": [0.4, d], "event": "posedge clk"}
                              for c, p, d in eps]}

    report = {"detailed_net_timings": [
        net("en", ("a_FF_Q_0", "CE", 4.7), ("a_FF_Q_1", "CE", 4.9), ("b_FF_Q", "CE", 4.2)),
        net("wa", ("ram0", "WAD3", 4.6), ("ram1", "WAD3", 4.55), ("ram1", "WAD0", 4.51)),
        net("rst", ("c_FF_Q", "LSR", 4.8)),
        net("late", ("a_FF_Q_0", "CE", 5.2)),  # the same endpoint later on another net
        net("x", ("d_FF_Q", "DI", 5.3), ("e_FF_Q", "M", 4.5), ("dsp", "B12", 4.9)),
        net("pin", ("f_FF_Q", "CE", 6.0), event="<async>"),
    ]}
    r = near_by_port(report, 5.0)
    assert r["endpoints"] == 8
    assert r["ports"] == {"WAD": 3, "CE": 2, "LSR": 1, "DI": 1, "B": 1}
    assert list(r["ports"])[:2] == ["WAD", "CE"]  # most first
    assert r["shared"] == [{"net": "wa", "endpoints": 3}, {"net": "en", "endpoints": 1},
                           {"net": "late", "endpoints": 1}, {"net": "rst", "endpoints": 1}]
    assert near_by_port(report, 5.0, listed=1)["shared"] == r["shared"][:1]
    # a wider margin takes in b's enable and e's data (4.5 is not later than 5.0 - 0.5)
    wide = near_by_port(report, 5.0, margin=0.81)
    assert wide["ports"]["CE"] == 3 and wide["ports"]["M"] == 1 and wide["endpoints"] == 10
    assert near_by_port({"critical_paths": []}, 5.0) is None


def test_fmax_by_stage_takes_each_stage_at_its_latest_endpoint(capsys):
    """The longest prefix wins (``detect.filter.`` before a shorter ``detect.``), a register
    of no stage is a join's, a cell's suffixes are the register's, and a path from a pin is
    not timed."""
    report = _report(("core.gate.fit1_TRELLIS_FF_Q_3", "DI", 5.0),
                     ("core.gate.hdrs.w_TRELLIS_FF_Q", "CE", 4.0),
                     ("core.detect.filter.k_TRELLIS_FF_Q", "M", 4.0),
                     ("core.detect.go_TRELLIS_FF_Q", "M", 3.2),
                     ("core.gate_slice.skid_TRELLIS_FF_Q", "DI", 2.5),
                     ("core.pack.mode_TRELLIS_FF_Q", "M", 9.9, "async"))
    stages = {"gate": "gate.", "filter": "detect.filter.", "detect": "detect.",
              "packetizer": "pack."}
    got = fmax_by_stage(report, stages, "core.")
    assert got == {"gate": 200.0, "filter": 250.0, "detect": 312.5, "joins": 400.0}
    assert list(got) == ["gate", "filter", "detect", "joins"]
    # out of context the same registers have no shell prefix: here every one is a join's
    assert fmax_by_stage(report, stages) == {"joins": 200.0}
    assert fmax_by_stage({}, stages) is None
    runs = [{"by_stage": {"a": 200.0, "b": 180.0, "joins": 250.0}},
            {"by_stage": {"a": 170.0, "b": 190.0, "joins": 240.0}}]
    assert stage_summary(runs) == {
        "a": {"mean_mhz": 185.0, "lowest_mhz": 170.0, "without_mean_mhz": 185.0},
        "b": {"mean_mhz": 185.0, "lowest_mhz": 180.0, "without_mean_mhz": 185.0},
        "joins": {"mean_mhz": 245.0, "lowest_mhz": 240.0, "without_mean_mhz": 175.0}}
    fig = {"fmax_mhz": 170.0, "luts": 1, "ffs": 1, "dsps": 0, "brams": 0, "lanes": 1,
           "samples_per_s": 170e6, "stages": stage_summary(runs)}
    print_table({"device": DEVICE, "components": {"albcap_pipeline": fig}})
    assert ("by stage, the mean MHz its endpoints allow (the pipeline's mean without them): "
            "a 185.0 (185.0); b 185.0 (185.0); joins 245.0 (175.0)") in capsys.readouterr().out


def test_pipeline_stages_name_the_pipelines_own_submodules():
    """Each prefix of :data:`PIPELINE_STAGES` is a submodule of the elaborated pipeline, so a
    renamed stage cannot leave its registers counted as a join's."""
    from amaranth.hdl import Fragment

    from hdl.pipeline import Pipeline

    def names(fragment, above=""):
        found = set()
        for sub, name, *_ in fragment.subfragments:
            found |= {above + name + "."} | names(sub, above + name + ".")
        return found

    inside = names(Fragment.get(Pipeline(), None))
    assert set(PIPELINE_STAGES.values()) <= inside, set(PIPELINE_STAGES.values()) - inside
    assert len(set(PIPELINE_STAGES.values())) == len(PIPELINE_STAGES)


def test_record_figures_merges_per_configuration(tmp_path):
    dev = {"family": "ecp5", "part": "LFE5U-85F", "speed": 6, "package": "CABGA381"}
    path = tmp_path / "fpga.json"
    fig = {"fmax_mhz": 100.0, "lanes": 1}
    record_figures(path, {"device": dev, "components": {"a": {**fig, "params": {}}}})
    record_figures(path, {"device": dev, "components": {
        "a": {**fig, "fmax_mhz": 90.0, "params": {"lanes": 4, "taps_max": 32}}}})
    got = json.loads(path.read_text())["figures"]
    assert set(got) == {"a", "a[lanes=4,taps_max=32]"}
    assert figure_key("a", {"taps_max": 32, "lanes": 4}) == "a[lanes=4,taps_max=32]"
    assert figure_key("a", {"lanes": 4}, "in") == "a[context=in,lanes=4]"
    assert figure_key("a", None, "in") == "a[context=in]"
    assert got["a"]["fmax_mhz"] == 100.0 and got["a[lanes=4,taps_max=32]"]["fmax_mhz"] == 90.0
    with pytest.raises(ValueError, match="holds figures for"):
        record_figures(path, {"device": {**dev, "part": "LFE5U-25F"}, "components": {}})
    # a redraw (the shell's chains reordered) is a null measurement: refused, nothing written
    before = path.read_bytes()
    with pytest.raises(ValueError, match=r"\['a'\] placed with the shell's chains redrawn "
                                         r"\(redraw=2\).*not a figure to record"):
        record_figures(path, {"device": dev, "components": {
            "a": {**fig, "params": {}, "context": "in", "redraw": 2}}})
    assert path.read_bytes() == before


def test_shell_redraw_reorders_its_chains():
    """``redraw``: bit 0 the input chain's ports in reverse order, bit 1 the static chain's;
    the core's ports take the bits shifted in, in that order, and nothing else changes."""
    from amaranth.sim import Simulator

    from hdl.stitch import Stitch
    from hdl.synth import PortShell

    rng = __import__("random").Random(7)
    for redraw in PortShell.REDRAWS:
        shell = PortShell(Stitch(), static="registers", redraw=redraw)
        static = [v for _, v in shell._pinned]
        chains = [(shell.din, shell._ins[::-1] if redraw & 1 else shell._ins),
                  (shell.cfg_din, static[::-1] if redraw & 2 else static)]
        want = [[rng.randrange(2) for _ in range(sum(len(v) for v in ports))]
                for _, ports in chains]
        sim = Simulator(shell)
        sim.add_clock(1e-8)

        async def bench(ctx, chains=chains, want=want, redraw=redraw):
            for k in reversed(range(max(len(w) for w in want))):
                for (pin, _), w in zip(chains, want, strict=True):
                    ctx.set(pin, w[k] if k < len(w) else 0)
                await ctx.tick()
            for (_, ports), w in zip(chains, want, strict=True):
                got = []
                for port in ports:
                    v = ctx.get(port)
                    got += [(v >> i) & 1 for i in range(len(port))]
                assert got == w, redraw

        sim.add_testbench(bench)
        sim.run()
    for bad in (4, -1, True, "1"):
        with pytest.raises(ValueError, match=r"redraw must be one of \(0, 1, 2, 3\), not "):
            PortShell(Stitch(), redraw=bad)
    with pytest.raises(ValueError, match=r"redraw=1 orders the shell's chains: in context"):
        synthesize("albcap_stitch", redraw=1)


def test_cli_refuses_to_record_a_redraw(tmp_path, capsys):
    out = tmp_path / "fpga.json"
    for extra, msg in ((["--context", "in", "--out", str(out)], "not a figure to record"),
                       ([], "give --context in")):
        with pytest.raises(SystemExit, match=msg):
            main(["hdl", "synth", "--component", "albcap_stitch", "--redraw", "1", *extra])
    assert not out.exists()


def test_a_faster_grade_places_the_same_netlist_faster(tmp_path):
    """``speed``: the grade reaches nextpnr (the same netlist on the same seed closes a
    shorter worst path on grade 8 than on grade 6), is in the result's device and in each
    figure, and a file of grade-6 figures refuses grade 8's, unchanged."""
    assert SPEEDS == (6, 7, 8) and DEVICE["speed"] == 6
    slow, fast = (synth_all(["albcap_stitch"], speed=s) for s in (6, 8))
    assert slow["device"] == DEVICE and fast["device"] == {**DEVICE, "speed": 8}
    r6, r8 = slow["components"]["albcap_stitch"], fast["components"]["albcap_stitch"]
    assert "speed" not in r6 and r8["speed"] == 8
    assert (r8["luts"], r8["ffs"], r8["dsps"]) == (r6["luts"], r6["ffs"], r6["dsps"])
    assert r8["fmax_mhz"] > 1.05 * r6["fmax_mhz"], (r6["fmax_mhz"], r8["fmax_mhz"])
    path = tmp_path / "fpga.json"
    record_figures(path, slow)
    before = path.read_bytes()
    with pytest.raises(ValueError, match=r"holds figures for .*'speed': 6.*, not .*'speed': 8"):
        record_figures(path, fast)
    assert path.read_bytes() == before


@pytest.mark.parametrize("bad", [5, 9, True, "8"])
def test_an_unknown_speed_grade_is_refused(bad, capsys):
    with pytest.raises(ValueError, match=rf"speed must be one of the LFE5U-85F's grades "
                                         rf"\(6, 7, 8\), not {bad!r}"):
        synthesize("albcap_stitch", speed=bad)
    with pytest.raises(ValueError, match="speed must be one of"):
        synth_all(["albcap_stitch"], speed=bad)
    if isinstance(bad, int) and not isinstance(bad, bool):
        with pytest.raises(SystemExit):
            main(["hdl", "synth", "--component", "albcap_stitch", "--speed", str(bad)])
        assert f"argument --speed: invalid choice: {bad}" in capsys.readouterr().err


def test_the_critical_mapping_is_synth_ecp5_as_it_is():
    """Every recorded figure's netlist: Yosys's own script, nothing in between."""
    assert MAPPINGS[0] == "critical"
    assert _yosys_script("albcap_stitch", "n.json") == (
        "read_verilog albcap_stitch.v; synth_ecp5 -top albcap_stitch -json n.json")
    # the average mapping runs synth_ecp5 around its own abc9 step, -t in &if
    script = _yosys_script("albcap_stitch", "n.json", "average")
    assert "-run :map_luts" in script and "-run map_cells: -json n.json" in script
    assert ",-t," in script and script.count("abc9") == 1


def test_an_unknown_mapping_is_refused():
    with pytest.raises(ValueError, match=r"mapping must be one of \('critical', 'average'\), "
                                         r"not 'delay'"):
        _yosys_script("albcap_stitch", "n.json", "delay")
    with pytest.raises(ValueError, match="mapping must be one of"):
        synthesize("albcap_stitch", mapping="delay")


def test_the_average_mapping_leaves_no_register_two_levels_deep_in_the_stitch():
    """Real Yosys runs (seconds): the stitch alone has registers two LUTs deep where ABC maps
    for area below its critical arrival, and none with the outputs' average level minimised;
    the same registers either way."""
    from hdl.synth import levels

    critical, average = (levels("albcap_stitch", mapping=m) for m in MAPPINGS)
    assert set(critical) == set(average)
    assert max(critical.values()) >= 2 and max(average.values()) == 1


@pytest.mark.parametrize("call", [
    "_run([sys.executable, '-c', TOOL], CWD, 'tool')",
    "_run_many([([sys.executable, '-c', TOOL], CWD, 'tool')] * 1, jobs=2)",
])
def test_a_stopped_run_stops_its_tool(tmp_path, call):
    """SIGTERM to a process running a tool through ``hdl.synth._run`` or ``_run_many``
    (nextpnr for an hour, say) kills the tool before the process exits, rather than leaving
    it orphaned."""
    import os
    import signal
    import subprocess
    import sys
    import time

    child_pid = tmp_path / "child.pid"
    tool = f"import os, time; open({str(child_pid)!r}, 'w').write(str(os.getpid())); time.sleep(60)"
    runner = ("import sys; from pathlib import Path; from hdl.synth import _run, _run_many; "
              f"TOOL, CWD = {tool!r}, Path({str(tmp_path)!r}); {call}")
    parent = subprocess.Popen([sys.executable, "-c", runner], cwd=os.getcwd())
    deadline = time.monotonic() + 30
    while not (child_pid.exists() and child_pid.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    pid = int(child_pid.read_text())
    parent.send_signal(signal.SIGTERM)
    assert parent.wait(timeout=30) == 128 + signal.SIGTERM
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def _stamping_tool(path, seconds: float) -> list[str]:
    """A stand-in tool (a Python child) that writes its pid, start and end times to ``path``."""
    import sys

    code = (f"import os, time; p = {str(path)!r}; t = time.time(); "
            f"open(p, 'w').write(f'{{os.getpid()}} {{t}}'); time.sleep({seconds}); "
            "open(p, 'a').write(f' {time.time()}')")
    return [sys.executable, "-c", code]


@pytest.mark.parametrize("jobs", [1, 2])
def test_run_many_runs_at_most_jobs_at_once(tmp_path, jobs):
    """``_run_many`` (``albcap hdl synth --jobs``): with one job the runs follow each other,
    with two the first two overlap; every run's seconds are returned in the order given."""
    from hdl.synth import _run_many

    runs = []
    for i in range(3):
        (tmp_path / f"{i}").mkdir()
        runs.append((_stamping_tool(tmp_path / f"{i}" / "t", 0.5), tmp_path / f"{i}", f"run {i}"))
    seconds = _run_many(runs, jobs)
    assert len(seconds) == 3 and all(s >= 0.5 for s in seconds)
    spans = [tuple(map(float, (tmp_path / f"{i}" / "t").read_text().split()[1:])) for i in range(3)]
    overlap = spans[1][0] < spans[0][1]
    assert overlap == (jobs == 2)
    assert spans[2][0] >= min(spans[0][1], spans[1][1])  # never three at once


def test_run_many_failure_kills_the_others_and_says_which(tmp_path):
    """A tool that fails stops the run with its name, exit status and output's tail, and the
    tools still running are killed, not left behind."""
    import os
    import sys
    import time

    from hdl.synth import _run_many

    for d in ("slow", "bad"):
        (tmp_path / d).mkdir()
    slow = (_stamping_tool(tmp_path / "slow" / "t", 60), tmp_path / "slow", "slow tool")
    fail = ("import time, sys; time.sleep(1); print('no route to the clock'); sys.exit(3)")
    bad = ([sys.executable, "-c", fail], tmp_path / "bad", "nextpnr-ecp5 on x, seed 2")
    t = time.monotonic()
    with pytest.raises(RuntimeError, match=r"seed 2 failed \(exit 3\):\nno route to the clock"):
        _run_many([slow, bad], jobs=2)
    assert time.monotonic() - t < 30
    pid = int((tmp_path / "slow" / "t").read_text().split()[0])
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    for bad_jobs in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="jobs must be a positive integer"):
            _run_many([slow], bad_jobs)


@pytest.mark.parametrize("bad", ["0", "-2", "two"])
def test_jobs_option_wants_a_positive_integer(bad, capsys):
    """``albcap hdl synth --jobs`` refuses what is not a positive integer, naming it."""
    with pytest.raises(SystemExit):
        main(["hdl", "synth", "--component", "albcap_stitch", "--jobs", bad])
    assert f"--jobs: wants a positive integer, not {bad!r}" in capsys.readouterr().err
