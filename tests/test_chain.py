"""model.chain end to end, the golden-vector writer, and the model's commands."""

import json

import numpy as np
import pytest

from firmware_host.cli import main
from model.bench import synthetic_codes, workload_bank
from model.chain import encode_frames, run_chain, run_chain_reference
from model.frame import unpack_frame
from model.gate import gate_events
from model.layouts import PEAK_RECORD, FrameFlag, FrameType
from model.registers import Config
from model.vectors import STAGES, stage_vectors, write_vectors


@pytest.fixture(scope="module")
def batch():
    return synthetic_codes(24, 700, seed=3), workload_bank(4, 16)


class TestChain:
    @pytest.mark.parametrize("mode", [0, 1])
    def test_vectorized_equals_per_frame_reference(self, batch, mode):
        adc, bank = batch
        cfg = Config(stitch_mode=mode, out_shift=12, bin_offset=27, bin_len=30)
        a = run_chain(adc, bank, cfg)
        b = run_chain_reference(adc, bank, cfg)
        np.testing.assert_array_equal(a.stitched, b.stitched)
        np.testing.assert_array_equal(a.filtered, b.filtered)
        np.testing.assert_array_equal(a.peaks.records()[0], b.peaks.records()[0])
        assert a.peaks.surface.found.sum() > 20  # the synthetic echoes are found

    def test_surface_floor_in_the_fused_loop_equals_the_reference(self, batch):
        """``min_surf`` moves the surface, and with it the template switches: the fused
        filter-and-detect loop against the per-frame reference, at a floor that half of the
        frames' first peaks fail."""
        adc, bank = batch
        cfg = Config(stitch_mode=1, out_shift=12, bin_offset=27, bin_len=30, min_thr=20)
        plain = run_chain(adc, bank, cfg).peaks
        floor = int(np.median(plain.surface.amplitude[plain.surface.found]))
        cfg = cfg.replace(min_surf=floor)
        a, b = run_chain(adc, bank, cfg), run_chain_reference(adc, bank, cfg)
        np.testing.assert_array_equal(a.filtered, b.filtered)
        np.testing.assert_array_equal(a.peaks.records()[0], b.peaks.records()[0])
        moved = a.peaks.surface.n != plain.surface.n
        assert moved.sum() >= 5 and np.all(a.peaks.surface.amplitude[a.peaks.surface.found]
                                           > floor)

    def test_frames_split_anywhere_give_the_same_results(self, batch):
        adc, bank = batch
        cfg = Config(stitch_mode=1, out_shift=12)
        whole = run_chain(adc, bank, cfg)
        parts = [run_chain(adc[i:i + 5], bank, cfg) for i in range(0, len(adc), 5)]
        np.testing.assert_array_equal(np.concatenate([p.filtered for p in parts]),
                                      whole.filtered)

    @pytest.mark.parametrize("ftype", list(FrameType))
    def test_encoded_frames_decode_to_the_results(self, batch, ftype):
        adc, bank = batch
        cfg = Config(stitch_mode=1, out_shift=12, frame_type=int(ftype), gate_len=700)
        r = run_chain(adc, bank, cfg)
        _, hdr = gate_events(np.arange(len(adc)) * 5000, [0], cfg)
        frames = encode_frames(adc, r, hdr, cfg)
        for i, buf in enumerate(frames):
            h, payload, end = unpack_frame(buf)
            assert end == len(buf) and h["shot"] == i and h["frame_type"] == ftype
            assert bool(h["flags"] & FrameFlag.SURFACE) == bool(r.peaks.surface.found[i])
            assert bool(h["flags"] & FrameFlag.BOTTOM) == bool(r.peaks.bottom.found[i])
            if ftype == FrameType.RAW:
                np.testing.assert_array_equal(payload, adc[i])
            elif ftype == FrameType.STITCHED:
                np.testing.assert_array_equal(payload, r.stitched[i])
            elif ftype == FrameType.FILTERED:
                np.testing.assert_array_equal(payload, r.filtered[i])
            else:
                rec = PEAK_RECORD.unpack(payload)
                if r.peaks.surface.found[i]:
                    assert rec["position_q8"][0] == r.peaks.surface.position_q8[i]

    def test_wrong_input(self, batch):
        _, bank = batch
        with pytest.raises(ValueError, match="adc must have dtype uint8, not float64"):
            run_chain(np.zeros((1, 3, 10)), bank, Config())


class TestVectors:
    def test_every_stage_is_reproducible(self):
        for stage in STAGES:
            a, b = stage_vectors(stage, 5), stage_vectors(stage, 5)
            for ca, cb in zip(a, b, strict=True):
                for k in ca["arrays"]:
                    np.testing.assert_array_equal(ca["arrays"][k], cb["arrays"][k])

    def test_stitch_edges_cover_thresholds_and_rails(self):
        case = stage_vectors("stitch")[0]
        codes = set(case["arrays"]["adc"].ravel().tolist())
        assert {0, 1, 199, 200, 201, 254, 255} <= codes

    def test_peak_vectors_hold_a_surface_the_floor_skips(self):
        """The ``surface_floor`` case: frames whose first peak over the threshold is a bump
        under ``min_surf`` (their surface without the floor), so a twin that ignores the
        register fails it."""
        from model.peak_detect import peak_detect

        case = next(c for c in stage_vectors("peak_detect") if c["name"] == "surface_floor")
        y, cfg = case["arrays"]["y"], case["config"]
        with_floor = peak_detect(y, 31, cfg).surface.n
        without = peak_detect(y, 31, cfg.replace(min_surf=0)).surface.n
        assert (with_floor != without).sum() >= 3

    def test_written_files_match_the_arrays(self, tmp_path):
        root = write_vectors("peak_detect", tmp_path)
        man = json.loads((root / "manifest.json").read_text())
        case = man["cases"][0]
        info = case["arrays"]["records"]
        arr = np.load(root / info["npy"])
        assert list(arr.shape) == info["shape"]
        hex_vals = [int(v, 16) for v in (root / info["hex"]).read_text().split()]
        assert hex_vals == arr.ravel().tolist()
        y = np.load(root / case["arrays"]["y"]["npy"])
        words = (root / case["arrays"]["y"]["hex"]).read_text().split()
        assert len(words[0]) == 8 and int(words[0], 16) == int(y.ravel()[0]) & 0xFFFFFFFF

    def test_unknown_stage(self):
        with pytest.raises(ValueError, match="stage must be one of"):
            stage_vectors("fft")


class TestCommands:
    def test_vectors_command(self, tmp_path, capsys):
        assert main(["vectors", "--stage", "stitch", "--out", str(tmp_path)]) == 0
        assert "stitch: 8 cases" in capsys.readouterr().out
        assert (tmp_path / "stitch" / "manifest.json").exists()

    def test_spec_check_command(self, capsys):
        assert main(["spec"]) == 0
        assert "matches the code" in capsys.readouterr().out

    def test_bench_model_small(self, capsys):
        assert main(["bench", "model", "--json", "--frames", "64", "--samples", "512",
                     "--baseline-frames", "8", "--repeats", "1"]) == 0
        res = json.loads(capsys.readouterr().out)
        assert res["bit_exact_vs_baseline"] is True
        assert res["frames_per_s"] > 0 and res["baseline_frames_per_s"] > 0
        assert {"speedup", "workload", "peak_rss_mb"} <= set(res)
