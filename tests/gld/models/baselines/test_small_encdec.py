import baseline_checks

from gld.models import baselines
from gld.models.baselines.small_encdec import SmallEncDec


def test_parameter_count_matches_the_papers_layers():
    # Encoder 8->16 (7x7), 16->32 (5x5), 32->54, 54->128 (3x3); decoder 3x3 convs
    # 128->128, (128+54)->64, (64+32)->32, (32+16)->16; prediction (16+8)->1, with biases.
    expected = (
        (7 * 7 * 8 * 16 + 16)
        + (5 * 5 * 16 * 32 + 32)
        + (9 * 32 * 54 + 54)
        + (9 * 54 * 128 + 128)
        + (9 * 128 * 128 + 128)
        + (9 * 182 * 64 + 64)
        + (9 * 96 * 32 + 32)
        + (9 * 48 * 16 + 16)
        + (9 * 24 + 1)
    )
    assert baselines.parameter_count(SmallEncDec(), 192, 256) == expected
    assert baselines.LEARNED["small_encdec"] is SmallEncDec


def test_shapes_at_paper_size_and_odd_tiny_size():
    outputs = baseline_checks.output_shapes(SmallEncDec(), 192, 256)
    assert "inv_depth_pyramid" not in outputs
    # 20x28 halves to 10x14, 5x7, 3x4, 2x2: up-sampling overshoots and must be cropped.
    baseline_checks.output_shapes(SmallEncDec(), 20, 28)


def test_training_lowers_sparse_loss():
    losses, outputs, _ = baseline_checks.train_tiny(SmallEncDec(), learning_rate=3e-4)
    baseline_checks.check_trained_outputs(losses, outputs)
