"""The demo's closing summary: every column per pair, cross-pair numbers apart, and what the FVU means."""

from __future__ import annotations

from steering_core.demo import format_summary


def summary(fvu_close: float) -> dict:
    return {
        "pairs": [
            {"layer": 1, "pair": "open_vs_close", "positive_rows": 441, "negative_rows": 434, "latent_norm": 2.8171,
             "residual_norm": 5.1644, "decoded_cosine": 0.7632, "fvu": (0.41, fvu_close)},
            {"layer": 1, "pair": "on_vs_off", "positive_rows": 441, "negative_rows": 504, "latent_norm": 3.5812,
             "residual_norm": 5.4719, "decoded_cosine": -0.1, "fvu": (0.3, 0.2)},
        ],
        "between": [{"layer": 1, "pairs": ("open_vs_close", "on_vs_off"), "residual_cosine": -0.0721,
                     "latent_cosine": 0.0583, "mean_difference_cosine": None}],
    }


def test_every_column_is_per_pair_and_cross_pair_numbers_have_their_own_table():
    text = format_summary(summary(0.5), random_sae=False)
    assert text.splitlines()[:4] == [
        "Steering vectors, per pair:",
        "layer    pair           rows +/-  latent norm  residual norm  cos(decoded, mean diff)  FVU +/-",
        "layer01  open_vs_close  441/434   2.817        5.164          0.763                    0.410 / 0.500",
        "layer01  on_vs_off      441/504   3.581        5.472          -0.100                   0.300 / 0.200",
    ]
    assert text.splitlines()[5:8] == [
        "Between pairs (cosine of the two pairs' directions):",
        "layer    pairs                       residual  latent  mean diff",
        "layer01  open_vs_close vs on_vs_off  -0.072    0.058   -",
    ]
    assert text.endswith("FVU (fraction of variance unexplained by the SAE) is at most 1 everywhere.")


def test_fvu_above_one_is_flagged_on_a_real_sae():
    text = format_summary(summary(1.7), random_sae=False)
    assert "0.410 / 1.700 !" in text
    assert "! FVU > 1 for open_vs_close (layer01): the SAE does not reconstruct these residuals" in text


def test_the_random_demo_sae_is_explained_not_flagged():
    text = format_summary(summary(5.3), random_sae=True)
    assert " !" not in text and "0.410 / 5.300" in text
    assert "The demo's borrowed SAEs are random (untrained, tiny)" in text and "nothing is broken" in text
    assert "listed below" not in text


def test_a_trained_sae_prints_its_verdict_and_table():
    record = {"layer": 1, "verdict": "trained reconstructs better: FVU 0.010 trained vs 3.700 borrowed", "saes": {
        name: {"name": name, "rows": {"rows": 711, "fvu": fvu, "l0": 8.0, "dead": 3, "dense": 1, "d_sae": 256},
               "actions": {"delta_recon": 0.05, "delta_zero": 0.66, "recovered": recovered}}
        for name, fvu, recovered in (("trained", 0.01, 0.924), ("borrowed", 3.7, None))}}
    text = format_summary(summary(5.3) | {"trained_saes": [record]}, random_sae=True)
    assert "the layers listed below steer through an SAE trained on the demo's own residuals" in text
    assert ("SAE trained on this run's residuals, layer 1, against the borrowed one (held-out episodes): "
            "trained reconstructs better: FVU 0.010 trained vs 3.700 borrowed") in text
    rows = [line for line in text.splitlines() if line.startswith(("trained (", "borrowed ("))]
    assert len(rows) == 2 and "0.010" in rows[0] and "0.924" in rows[0] and "3.700" in rows[1] and "—" in rows[1]


def test_the_evaluation_answer_ends_the_summary():
    from steering_core.demo import TINY_MODEL_NOTE

    row = {"pair": "open_vs_close", "layer": "layer 2", "direction": "residual_direction", "alpha": 2.0,
           "alpha_vector": 0.25, "reversed": False, "efficacy": 0.9, "efficacy_negative": 0.8,
           "efficacy_negative_ci": [0.5, 1.0], "efficacy_positive": 1.0, "efficacy_positive_ci": [0.75, 1.25],
           "p_random": 0.02, "note": TINY_MODEL_NOTE}
    lines = format_summary(summary(0.5) | {"evaluation": [row]}, random_sae=True).splitlines()
    assert "open_vs_close  residual_direction, layer 2  2 / 0.25" in lines[-4]
    assert "0.800 [0.500, 1.000]" in lines[-4] and "1.000 [0.750, 1.250]" in lines[-4] and lines[-4].endswith("0.020")
    assert lines[-2] == ("open_vs_close: residual_direction at layer 2 moves the actions 0.900 of the way to the other "
                         "task's instruction (cross-fitted), better than random directions of the residual stream "
                         "(p = 0.020).")
    assert lines[-1].startswith("The demo's policy is tiny and random") and "mean nothing" in lines[-1]
