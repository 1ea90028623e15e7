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
    def test_equal_energy_and_full_scale(self):
        b = coeffs.bank_from_templates(templates())
        e = np.linalg.norm(b.coefs.astype(float), axis=1)
        assert np.ptp(e) / e.mean() < 1e-3
        assert np.abs(b.coefs).max() == 32767  # the narrowest template uses the full range

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
        with pytest.raises(ValueError, match="template 2 is all zeros"):
            coeffs.bank_from_templates(t)

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
