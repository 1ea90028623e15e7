"""firmware_host.coeffs: quantization, equal energy, SNR loss, shift choice, files."""

import json

import numpy as np
import pytest

from firmware_host import coeffs
from model.matched_filter import K_MAX, L_MAX, Bank, matched_filter
from model.registers import Config


def templates(K=4, L=32):
    return np.stack([coeffs.gaussian_pulse(4 + 3 * k, L, centre=8 + k) for k in range(K)])


class TestQuantize:
    def test_equal_dc_gain_and_full_scale(self):
        b = coeffs.bank_from_templates(templates())
        dc = b.coefs.astype(float).sum(axis=1)
        assert np.ptp(dc) / dc.mean() < 1e-3
        assert np.abs(b.coefs).max() == 32767  # the narrowest template uses the full range
        # broader templates: less noise gain than template 0 for the same DC gain
        e = np.linalg.norm(b.coefs.astype(float), axis=1)
        assert np.all(np.diff(e) < 0)

    def test_equal_energy_and_full_scale(self):
        b = coeffs.bank_from_templates(templates(), normalize="energy")
        e = np.linalg.norm(b.coefs.astype(float), axis=1)
        assert np.ptp(e) / e.mean() < 1e-3
        assert np.abs(b.coefs).max() == 32767

    def test_unknown_normalization(self):
        with pytest.raises(ValueError,
                           match="normalize must be 'dc', 'energy' or 'noise', not 'peak'"):
            coeffs.bank_from_templates(templates(), normalize="peak")

    def test_equal_noise_for_a_given_noise(self):
        # white noise: the same as equal energy; a low-pass noise weighs broad templates more
        t = templates()
        white = coeffs.bank_from_templates(t, normalize="noise", noise_rms=np.linalg.norm)
        energy = coeffs.bank_from_templates(t, normalize="energy")
        assert np.abs(white.coefs.astype(int) - energy.coefs).max() <= 1
        lags = np.arange(-31, 32)
        r = np.exp(-lags ** 2 / 8.0)  # a Gaussian autocorrelation of 2 samples

        def red(c):
            return np.sqrt(np.correlate(c, c, "full") @ r)

        b = coeffs.bank_from_templates(t, normalize="noise", noise_rms=red)
        out = np.array([red(c) for c in b.coefs.astype(float)])
        assert np.ptp(out) / out.mean() < 1e-3
        assert np.abs(b.coefs).max() == 32767

    def test_noise_normalization_needs_its_noise(self):
        with pytest.raises(ValueError, match="normalize='noise' needs noise_rms.*got None"):
            coeffs.bank_from_templates(templates(), normalize="noise")
        with pytest.raises(ValueError, match=r"noise_rms must give finite values >= 0, gave "
                                             r"\[nan"):
            coeffs.bank_from_templates(templates(), normalize="noise",
                                       noise_rms=lambda c: float("nan"))
        t = templates()
        t[1] = 0
        with pytest.raises(ValueError, match="template 1 is of zero noise gain"):
            coeffs.bank_from_templates(t, normalize="noise", noise_rms=np.linalg.norm)

    def test_snr_loss_is_small_and_positive(self):
        t = templates()
        loss = coeffs.quantization_snr_loss_db(t, coeffs.bank_from_templates(t))
        assert np.all(loss >= 0) and np.all(loss < 1e-6)

    def test_coarse_quantization_loses_more(self):
        t = templates(K=1)
        fine = coeffs.bank_from_templates(t)
        coarse = Bank((fine.coefs // 4096 * 4096).astype(np.int16))
        lf = coeffs.quantization_snr_loss_db(t, fine)[0]
        lc = coeffs.quantization_snr_loss_db(t, coarse)[0]
        assert lc > lf

    def test_ref_offsets_default_to_peaks(self):
        b = coeffs.bank_from_templates(templates())
        assert b.ref_offsets.tolist() == [8.0, 9.0, 10.0, 11.0]

    def test_zero_template_refused(self):
        t = templates()
        t[2] = 0
        with pytest.raises(ValueError, match="template 2 is of zero sum"):
            coeffs.bank_from_templates(t)
        with pytest.raises(ValueError, match="template 2 is all zeros"):
            coeffs.bank_from_templates(t, normalize="energy")

    def test_too_many_templates(self):
        with pytest.raises(ValueError, match=r"templates must have shape \(K <= 16, L <= 64\)"):
            coeffs.bank_from_templates(np.ones((17, 4)))


class TestOutShift:
    @pytest.mark.parametrize("x_lo,x_hi", [(0, 765), (-800, 24700), (-32768, 32767)])
    def test_smallest_shift_that_cannot_saturate(self, x_lo, x_hi):
        b = coeffs.bank_from_templates(templates(K=1))
        s = coeffs.out_shift_for(b, x_lo, x_hi)
        # The worst input puts each tap's extreme under it: the filter output at the last
        # tap is then the largest possible accumulator value.
        worst = np.where(b.coefs[0] > 0, x_hi, x_lo).astype(np.int16)
        acc = int(np.dot(b.coefs[0].astype(np.int64), worst))
        y = matched_filter(worst[None, :], b, Config(out_shift=s))[0, -1]
        assert y == (acc + (1 << s >> 1)) >> s < 2**23  # exact, not clipped
        assert s > 0 and (acc + (1 << (s - 1) >> 1)) >> (s - 1) >= 2**23  # one less would clip


class TestFiles:
    def test_json_roundtrip(self, tmp_path):
        b = coeffs.bank_from_templates(templates(), bank_id=7)
        coeffs.save_bank_json(tmp_path / "b.json", b, depth_bin_m=1.1)
        b2, meta = coeffs.load_bank_json(tmp_path / "b.json")
        assert b2 == b and meta == {"depth_bin_m": 1.1}

    def test_hex_roundtrip_and_layout(self, tmp_path):
        b = coeffs.bank_from_templates(templates(K=3, L=5))
        coeffs.write_bank_hex(tmp_path / "b.hex", b)
        words = [w for w in (tmp_path / "b.hex").read_text().splitlines() if not w.startswith("//")]
        assert len(words) == K_MAX * L_MAX
        assert int(words[L_MAX + 2], 16) == int(b.coefs[1, 2]) & 0xFFFF
        assert coeffs.read_bank_hex(tmp_path / "b.hex", 3, 5, b.ref_offsets) == b

    @pytest.mark.parametrize("mutate,message", [
        (lambda d: d.update(format="x"), "format must be 'albcap-bank-1', not 'x'"),
        (lambda d: d["coefs"][1].__setitem__(3, 40000), r"coefs\[1\]\[3\] must be in -32768"),
        (lambda d: d["coefs"][0].pop(), "coefs must be a K x L list of integers"),
        (lambda d: d.update(K=5), r"coefs shape \(4, 32\) does not match K=5"),
        (lambda d: d["coefs"][0].__setitem__(0, 1.5), "coefs must be a K x L list of integers"),
        (lambda d: d.update(ref_offsets=[0, 1]), r"ref_offsets must have shape \(4,\)"),
    ])
    def test_bad_json_is_refused_whole(self, tmp_path, mutate, message):
        b = coeffs.bank_from_templates(templates())
        coeffs.save_bank_json(tmp_path / "b.json", b)
        doc = json.loads((tmp_path / "b.json").read_text())
        mutate(doc)
        (tmp_path / "b.json").write_text(json.dumps(doc))
        with pytest.raises(ValueError, match=message):
            coeffs.load_bank_json(tmp_path / "b.json")

    def test_not_json(self, tmp_path):
        (tmp_path / "b.json").write_text("{")
        with pytest.raises(ValueError, match="not JSON"):
            coeffs.load_bank_json(tmp_path / "b.json")

    def test_hex_wrong_length(self, tmp_path):
        (tmp_path / "b.hex").write_text("0001\n")
        with pytest.raises(ValueError, match="must hold 1024 words, not 1"):
            coeffs.read_bank_hex(tmp_path / "b.hex", 1, 1)


@pytest.fixture(scope="session")
def made():
    from sim.scene import preset

    return coeffs.scene_bank(preset("seed000"), n_templates=4, n_taps=48, mc_packets=20000)


class TestSceneBank:

    def test_geometry_and_registers(self, made):
        assert made.bank.K == 4 and made.bank.L == 48
        assert made.bin_depths_m[0] == 0 and np.all(np.diff(made.bin_depths_m) > 0)
        # seed000 at 2 GS/s and 10 deg: 5.6 cm of depth per sample, template 1 from 3 m
        assert made.bin_offset == round(3.0 / 0.05589)
        assert 16 <= made.bin_offset and made.bin_len > 100
        assert np.all(made.snr_loss_db < 1e-3)

    def test_templates_share_noise_gain_and_centroid(self, made):
        from sim.scene import preset

        h = made.bank.coefs.astype(float)
        floor = np.array([coeffs.filtered_floor_rms(preset("seed000"), t, 0) for t in h])
        assert np.ptp(floor) / floor.mean() < 1e-3
        # the broad deep returns need a larger sum of taps for the same noise
        dc = h.sum(axis=1)
        assert np.all(np.diff(dc) > 0) and dc[-1] > 1.5 * dc[0]
        centroid = (h * np.arange(48)).sum(axis=1) / dc
        whole = made.coverage > 0.95  # returns whose tail the window holds
        assert whole.sum() >= 2
        assert np.all(np.abs(centroid[whole] - 23.5) < 1.5)

    def test_deeper_returns_are_broader_and_cut_off_tails_are_reported(self, made):
        t = made.templates / made.templates.max(axis=1, keepdims=True)
        width = (t > 0.5).sum(axis=1)
        whole = made.coverage > 0.95
        assert np.all(np.diff(width[whole]) >= 0) and width[whole][-1] > width[0]
        assert made.coverage[-1] < made.coverage[1]  # the 34 m return outgrows 24 ns

    def test_bins_past_the_waters_reach_repeat_the_deepest_return(self):
        import dataclasses

        from sim.scene import preset

        # 8 mg/L of sediment: no packet comes back from the deeper bins
        turbid = dataclasses.replace(preset("seed000"), sediment_mg_l=8.0)
        sb = coeffs.scene_bank(turbid, n_templates=8, merge_equal=False)
        np.testing.assert_array_equal(sb.bank.coefs[-1], sb.bank.coefs[-2])
        assert len({row.tobytes() for row in sb.bank.coefs}) > 2
        # merged, the deepest return that came back serves every bin past it
        merged = coeffs.scene_bank(turbid, n_templates=8)
        assert 2 < merged.bank.K < 8 and merged.bin_offset == sb.bin_offset
        np.testing.assert_array_equal(merged.bank.coefs, sb.bank.coefs[:merged.bank.K])
        np.testing.assert_array_equal(merged.bank.coefs[-1], sb.bank.coefs[-1])

    def test_water_that_returns_nothing_gets_the_pulse_everywhere(self):
        import dataclasses

        from sim.scene import preset

        mud = dataclasses.replace(preset("seed000"), sediment_mg_l=300.0)
        sb = coeffs.scene_bank(mud, n_templates=4, merge_equal=False)
        c = sb.bank.coefs.astype(np.int64)
        # the same Gaussian, sampled on the Monte Carlo time grid and put back on the taps
        assert np.abs(c[1:] - c[0]).max() <= 0.01 * c[0].max()
        assert coeffs.scene_bank(mud, n_templates=4).bank.K == 1  # equal: merged

    def test_water_the_scene_says_does_not_stretch_gets_the_pulse_everywhere(self):
        import dataclasses

        from sim.scene import preset
        from sim.waveform import resolve_fidelity

        # a tolerance no stretching reaches: the simulator renders the bottom as the pulse
        flat = dataclasses.replace(preset("seed000"), fidelity_tolerance_m=10.0)
        assert resolve_fidelity(flat) == "analytic"
        sb = coeffs.scene_bank(flat, n_templates=4, n_taps=48, merge_equal=False)
        c = sb.bank.coefs.astype(np.int64)
        assert np.abs(c[1:] - c[0]).max() <= 1
        np.testing.assert_allclose(sb.bank.ref_offsets, 23.5)
        np.testing.assert_allclose(sb.coverage, 1.0, atol=1e-6)
        # equal templates are merged by default: the pulse alone, the fixed filter
        merged = coeffs.scene_bank(flat, n_templates=4, n_taps=48)
        assert merged.bank.K == 1 and merged.templates.shape == (1, 48)
        np.testing.assert_array_equal(merged.bank.coefs[0], sb.bank.coefs[0])
        assert merged.bin_offset == sb.bin_offset + 3 * sb.bin_len
        assert (merged.min_thr, merged.out_shift) == (sb.min_thr, sb.out_shift)

    def test_a_stretched_scene_gets_its_laws_returns(self):
        import dataclasses

        from sim.scene import preset
        from sim.stretching import law_for_scene
        from sim.waveform import resolve_fidelity

        sc = dataclasses.replace(preset("seed000"), fidelity_tolerance_m=2.0)
        assert resolve_fidelity(sc) == "stretched"
        sb = coeffs.scene_bank(sc, n_templates=4, n_taps=48)
        law = law_for_scene(sc, sc.max_depth_m)
        d = sb.bin_depths_m[1:]
        # the centroid of an exponentially modified Gaussian lies shift + tau after the hit,
        # and the template puts it in the window's middle
        want = 23.5 - (law.shift_s(d) + law.tau_s(d)) / sc.dt_s
        np.testing.assert_allclose(sb.bank.ref_offsets[1:], want, atol=0.02)
        assert np.all(np.diff(sb.bank.ref_offsets) < 0)

    def test_the_floor_is_measured_through_the_filter(self):
        """``min_thr``'s deviation against the filter output of the simulator's own floor: the
        lead-in of shots without sun or dark current, stitched and filtered by the model."""
        import dataclasses

        from model.chain import run_chain
        from sim.scene import preset
        from sim.shots import make_shots

        scene = dataclasses.replace(coeffs.survey_scene(preset("seed000")), depth_m=5.0,
                                    max_depth_m=5.0, solar_radiance_w_m2_sr_nm=0.0,
                                    dark_current_a=0.0)
        sb = coeffs.scene_bank(scene, n_templates=1, n_taps=64)
        shots = make_shots(scene, 5.0, 300, seed=2024)
        cfg = Config(**coeffs.survey_registers(sb), gate_len=shots.adc.shape[-1])
        y = run_chain(shots.adc, sb.bank, cfg).filtered.astype(np.float64)
        lead = int(shots.truth_surface_s.min() / scene.dt_s) - 8  # before the surface's echo
        measured = y[:, 63:lead].std()
        want = coeffs.filtered_floor_rms(scene, sb.bank.coefs[0], sb.out_shift)
        assert abs(measured / want - 1) < 0.05
        white = coeffs.filtered_floor_rms(scene, sb.bank.coefs[0], sb.out_shift,
                                          coeffs.noise_floor_lsb(scene))
        assert measured / white > 1.3  # the floor taken as white: 26 LSB against 37
        assert sb.min_thr == int(np.ceil(coeffs.MIN_THR_SIGMAS * want))
        # the floor's noise reading: the detector's mean absolute deviation of that noise
        dev = np.abs(y[:, 63:lead] - y[:, 63:lead].mean()).mean()
        assert abs(sb.floor_noise / dev - 1) < 0.06 and sb.floor_noise <= dev

    def test_out_shift_cannot_saturate(self, made):
        assert made.out_shift == coeffs.out_shift_for(made.bank, -800, 24700)


class TestDemo:
    def test_bit_exact_chain_measures_simulated_depths(self):
        from model.demo import demo_rows

        rows = demo_rows("seed000", [5.0, 10.0], shots=40, seed=2)
        for r in rows:
            assert r["detected"] == r["shots"]
            assert abs(r["bias_m"]) < 0.10 and r["std_m"] < 0.05

    def test_merged_surface_and_bottom_is_flagged_not_guessed(self):
        from model.demo import demo_rows

        (r,) = demo_rows("seed000", [0.5], shots=20, seed=2)
        assert r["detected"] == 0  # 0.5 m: one return, no confident wrong depth

    def test_command(self, capsys):
        from firmware_host.cli import main

        assert main(["demo", "--depths", "5", "--shots", "10"]) == 0
        out = capsys.readouterr().out
        assert "true m" in out and "5.00" in out

    def test_bad_depths(self, capsys):
        from firmware_host.cli import main

        assert main(["demo", "--depths", "5,x"]) == 2
        assert "--depths must be comma-separated numbers of metres" in capsys.readouterr().err


class TestDistinctTemplates:
    """``distinct_templates``: equal bins dropped where template selection allows it."""

    @staticmethod
    def bank(rows, ref=None):
        base = templates(K=3, L=16)
        t = np.stack([base[r] for r in rows])
        b = coeffs.bank_from_templates(t)
        return Bank(b.coefs, ref if ref is not None else np.full(len(rows), 5.0))

    @pytest.mark.parametrize("rows, keep, lead", [
        ([0, 0, 1, 2, 2, 2], [0, 2, 3], 1),   # a lead run and a trailing run
        ([0, 1, 1, 2], [0, 1, 2, 3], 0),      # a run in the middle stays (bins are uniform)
        ([0, 0, 0], [0], 2),                  # all equal: the fixed filter
        ([0, 1, 2], [0, 1, 2], 0),
        ([0], [0], 0),
        ([0, 1, 1], [0, 1], 0),
    ])
    def test_runs(self, rows, keep, lead):
        assert coeffs.distinct_templates(self.bank(rows)) == (keep, lead)

    def test_one_lsb_is_rounding_and_two_are_not(self):
        b = self.bank([0, 0])
        c = b.coefs.copy()
        c[1, 3] += 1
        assert coeffs.distinct_templates(Bank(c, b.ref_offsets)) == ([0], 1)
        c[1, 3] += 1
        assert coeffs.distinct_templates(Bank(c, b.ref_offsets)) == ([0, 1], 0)

    def test_equivalent_templates_by_their_snr_loss(self):
        # Gaussians of width 4, 4.05 (0.0008 dB apart), 6 (0.7 dB), 9, 9.1: equal taps only
        # keep all five; with a tolerance the lead and the trailing pair merge
        t = np.stack([coeffs.gaussian_pulse(w, 32) for w in (4, 4.05, 6, 9, 9.1)])
        b = coeffs.bank_from_templates(t)
        assert coeffs.distinct_templates(b) == ([0, 1, 2, 3, 4], 0)
        assert coeffs.distinct_templates(b, 0.05) == ([0, 2, 3], 1)
        assert coeffs.distinct_templates(b, 1.0) == ([0, 3], 2)
        with pytest.raises(ValueError, match="max_loss_db must be a number in 0..3 dB, not -1"):
            coeffs.distinct_templates(b, -1)

    def test_trailing_run_is_judged_against_the_template_kept(self):
        # 9, 10.4, 12: each under 0.05 dB from its neighbour, but 12 is 0.18 dB from 9
        t = np.stack([coeffs.gaussian_pulse(w, 48) for w in (4, 9, 10.4, 12)])
        b = coeffs.bank_from_templates(t)
        step = coeffs.mismatch_loss_db(b.coefs[2], b.coefs[3])
        far = coeffs.mismatch_loss_db(b.coefs[1], b.coefs[3])
        assert step < 0.06 < far
        assert coeffs.distinct_templates(b, 0.06) == ([0, 1, 2], 0)

    def test_mismatch_loss_of_two_gaussians(self):
        # sampled Gaussians of rms s1, s2: the continuous loss -10 log10(2 s1 s2 / (s1^2+s2^2))
        a, b = (coeffs.gaussian_pulse(f, 64) for f in (8.0, 12.0))
        s1, s2 = 8.0, 12.0
        want = -10 * np.log10(2 * s1 * s2 / (s1 ** 2 + s2 ** 2))
        assert coeffs.mismatch_loss_db(a, b) == pytest.approx(want, abs=1e-4)
        assert coeffs.mismatch_loss_db(b, a) == pytest.approx(want, abs=1e-9 + want * 1e-9)
        assert coeffs.mismatch_loss_db(a, 3 * a) == 0.0
        assert coeffs.mismatch_loss_db(a, -a) == np.inf
        with pytest.raises(ValueError, match="not all zeros"):
            coeffs.mismatch_loss_db(a, np.zeros(64))

    def test_a_different_reference_offset_is_a_different_template(self):
        # the same taps read at another event time give another depth
        assert coeffs.distinct_templates(self.bank([0, 0], ref=[5.0, 5.5])) == ([0, 1], 0)
        assert coeffs.distinct_templates(self.bank([0, 0], ref=[5.0, 5.001])) == ([0], 1)
