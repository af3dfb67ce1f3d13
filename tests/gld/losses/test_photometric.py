import cv2
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from gld import contract, geometry
from gld.losses import photometric

HEIGHT, WIDTH = 24, 32
# Normalised intrinsics with an off-centre principal point: fx = 32 px, fy = 24 px.
INTRINSICS = np.asarray([1.0, 1.0, 0.45, 0.55], np.float32)
# Compiled whole: on CPU much faster than op-by-op dispatch of the same functions.
warp_to_view1 = jax.jit(photometric.warp_to_view1)
self_supervised_loss = jax.jit(photometric.self_supervised_loss, static_argnums=2)


def texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A smooth random colour texture [H, W, 3] in [-0.5, 0.5]."""
    noise = rng.uniform(0.0, 1.0, (height, width, 3)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), 1.5)
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min())
    return smooth - 0.5


def shifted_pair(shift: int = 2, depth: float = 4.0, seed: int = 0):
    """A fronto-parallel plane at `depth` seen by a camera translated along x.

    The flow is a constant `shift` pixels: image2(u + shift, v) = image1(u, v).

    Returns:
      a batch of one pair (image1, image2, intrinsics1/2, rotation, translation) and the
      true view-1 depth [1, H, W].
    """
    canvas = texture(np.random.default_rng(seed), HEIGHT, WIDTH + shift)
    fx = INTRINSICS[0] * WIDTH
    batch = {
        "image1": canvas[None, :, shift:],
        "image2": canvas[None, :, :WIDTH],
        "intrinsics1": INTRINSICS[None],
        "intrinsics2": INTRINSICS[None],
        "rotation": np.eye(3, dtype=np.float32)[None],
        "translation": np.asarray([[shift * depth / fx, 0.0, 0.0]], np.float32),
    }
    return batch, np.full((1, HEIGHT, WIDTH), depth, np.float32)


def pose_outputs(batch, inv_depth_scales):
    return {
        "inv_depth_scales": tuple(inv_depth_scales),
        "rotation": jnp.asarray(batch["rotation"]),
        "translation": jnp.asarray(batch["translation"]),
    }


def test_sample_bilinear_by_hand():
    image = np.arange(12, dtype=np.float32).reshape(1, 3, 4, 1)  # value = 4 v + u
    pixels = np.asarray([[[[1.5, 0.25], [3.0, 2.0], [-5.0, 1.0], [9.0, 7.0]]]], np.float32)
    values = photometric.sample_bilinear(jnp.asarray(image), jnp.asarray(pixels))
    # Inside the image bilinear interpolation of a linear ramp is exact; outside, the
    # nearest edge pixel is repeated.
    np.testing.assert_allclose(values[0, 0, :, 0], [2.5, 11.0, 4.0, 11.0], atol=1e-6)


def test_reprojection_follows_gld_geometry():
    rng = np.random.default_rng(4)
    depth = rng.uniform(2.0, 6.0, (2, HEIGHT, WIDTH)).astype(np.float32)
    intrinsics1 = np.stack([INTRINSICS, [0.8, 1.2, 0.5, 0.5]]).astype(np.float32)
    intrinsics2 = np.stack([[1.1, 0.9, 0.52, 0.4], INTRINSICS]).astype(np.float32)
    rotation = geometry.rotation_matrix(rng.normal(0.0, 0.1, (2, 3))).astype(np.float32)
    translation = rng.normal(0.0, 0.5, (2, 3)).astype(np.float32)
    pixels2, valid = photometric.reproject(
        jnp.asarray(depth), rotation, translation, intrinsics1, intrinsics2
    )
    flow, depth2 = geometry.depth_to_flow(
        depth.astype(np.float64),
        geometry.intrinsics_matrix(intrinsics1.astype(np.float64), HEIGHT, WIDTH),
        geometry.intrinsics_matrix(intrinsics2.astype(np.float64), HEIGHT, WIDTH),
        rotation.astype(np.float64),
        translation.astype(np.float64),
    )
    expected = geometry.pixel_grid(HEIGHT, WIDTH) + flow
    inside = (np.abs(expected - [WIDTH / 2 - 0.5, HEIGHT / 2 - 0.5]) < [WIDTH / 2, HEIGHT / 2]).all(
        -1
    )
    np.testing.assert_allclose(pixels2, expected, atol=2e-3)
    np.testing.assert_array_equal(valid, inside & (depth2 > 0))
    assert 0.2 < np.mean(valid) < 1.0


def test_identity_pose_returns_the_image():
    rng = np.random.default_rng(1)
    image2 = texture(rng, HEIGHT, WIDTH)[None]
    depth = rng.uniform(1.0, 5.0, (1, HEIGHT, WIDTH)).astype(np.float32)
    warped, valid = warp_to_view1(
        jnp.asarray(image2),
        jnp.asarray(depth),
        jnp.eye(3)[None],
        jnp.zeros((1, 3)),
        jnp.asarray(INTRINSICS[None]),
    )
    np.testing.assert_allclose(warped, image2, atol=1e-4)
    assert bool(jnp.all(valid))


def test_known_shift_reprojects_exactly_with_the_true_depth_and_pose():
    shift = 2
    batch, depth = shifted_pair(shift)
    errors = {}
    for name, factor in (("true", 1.0), ("far", 2.0), ("near", 0.5)):
        warped, valid = warp_to_view1(
            jnp.asarray(batch["image2"]),
            jnp.asarray(depth * factor),
            jnp.asarray(batch["rotation"]),
            jnp.asarray(batch["translation"]),
            jnp.asarray(batch["intrinsics1"]),
        )
        error = photometric.photometric_error(warped, jnp.asarray(batch["image1"]))
        # Pixels whose 3x3 SSIM window lies in the view-2 part of the image (and in the
        # image: SSIM pads by reflection).
        inside = np.asarray(error)[0, 1:-1, 1 : WIDTH - shift - 1]
        errors[name] = float(np.mean(inside))
        if name == "true":
            assert np.asarray(valid)[0, :, : WIDTH - shift].all()
            assert not np.asarray(valid)[0, :, WIDTH - shift + 1 :].any()
    assert errors["true"] < 1e-5, errors
    assert errors["far"] > 0.02 and errors["near"] > 0.02, errors


def test_whole_loss_is_lowest_at_the_true_depth():
    batch, depth = shifted_pair(2)
    losses = {
        factor: float(
            self_supervised_loss(pose_outputs(batch, [1.0 / (depth * factor)]), batch)[1][
                "photometric"
            ]
        )
        for factor in (0.5, 0.8, 1.0, 1.25, 2.0)
    }
    assert min(losses, key=losses.get) == 1.0, losses
    # Only the right-hand columns that leave image 2 (identity error) and the SSIM windows
    # at that boundary are left at the true depth.
    assert losses[1.0] < 0.3 * losses[2.0], losses


def test_ssim_of_identical_images_is_one_and_matches_a_hand_window():
    rng = np.random.default_rng(2)
    x = texture(rng, 8, 9)[None]
    y = np.clip(x + rng.normal(0.0, 0.1, x.shape).astype(np.float32), -0.5, 0.5)
    np.testing.assert_allclose(photometric.ssim(jnp.asarray(x), jnp.asarray(x)), 1.0, atol=1e-5)

    value = np.asarray(photometric.ssim(jnp.asarray(x), jnp.asarray(y)))
    # Interior pixel (3, 4), channel 1, by the textbook formula on [0, 1] intensities.
    window_x = x[0, 2:5, 3:6, 1].astype(np.float64) + 0.5
    window_y = y[0, 2:5, 3:6, 1].astype(np.float64) + 0.5
    mean_x, mean_y = window_x.mean(), window_y.mean()
    var_x, var_y = window_x.var(), window_y.var()
    cov = np.mean((window_x - mean_x) * (window_y - mean_y))
    c1, c2 = 0.01**2, 0.03**2
    expected = ((2 * mean_x * mean_y + c1) * (2 * cov + c2)) / (
        (mean_x**2 + mean_y**2 + c1) * (var_x + var_y + c2)
    )
    np.testing.assert_allclose(value[0, 3, 4, 1], expected, rtol=1e-4)
    assert expected < 0.95


def test_photometric_error_of_constant_images_by_hand():
    a = np.full((1, 5, 5, 3), 0.1, np.float32)  # 0.6 on the [0, 1] scale
    b = np.full((1, 5, 5, 3), -0.1, np.float32)  # 0.4
    ssim = (2 * 0.6 * 0.4 + 1e-4) / (0.6**2 + 0.4**2 + 1e-4)  # variances are 0
    expected = 0.85 * (1 - ssim) / 2 + 0.15 * 0.2
    error = photometric.photometric_error(jnp.asarray(a), jnp.asarray(b))
    assert error.shape == (1, 5, 5)
    # float32 window variances (E[x^2] - E[x]^2) are zero only to ~1e-8.
    np.testing.assert_allclose(error, expected, rtol=2e-3)
    np.testing.assert_allclose(photometric.photometric_error(jnp.asarray(a), jnp.asarray(a)), 0.0)


def static_patch_pair(shift: int = 2):
    """`shifted_pair` in which rows 8..15, columns 4..19 moved with the camera: image 2
    equals image 1 there. Returns the batch, the true depth and the patch [H, W]."""
    batch, depth = shifted_pair(shift)
    static = np.zeros((HEIGHT, WIDTH), bool)
    static[8:16, 4:20] = True
    image2 = batch["image2"].copy()
    image2[0, static] = batch["image1"][0, static]
    return dict(batch, image2=image2), depth, static


def auto_mask_of(batch, depth):
    warped, valid = warp_to_view1(
        jnp.asarray(batch["image2"]),
        jnp.asarray(depth),
        jnp.asarray(batch["rotation"]),
        jnp.asarray(batch["translation"]),
        jnp.asarray(batch["intrinsics1"]),
    )
    error, auto_mask = photometric.minimum_reprojection_error(
        jnp.asarray(batch["image1"]), jnp.asarray(batch["image2"]), warped, valid
    )
    return np.asarray(error)[0], np.asarray(auto_mask)[0]


def test_auto_mask_masks_a_static_region():
    shift = 2
    batch, depth, _ = static_patch_pair(shift)
    error, auto_mask = auto_mask_of(batch, depth)
    # Static pixels whose 3x3 window is static: identity error 0, reprojection error not.
    assert auto_mask[9:15, 5:19].all()
    np.testing.assert_allclose(error[9:15, 5:19], 0.0, atol=1e-6)
    # Moving pixels whose reprojection window stays clear of the static region and in view.
    moving = np.ones((HEIGHT, WIDTH), bool)
    moving[6:18, 1:22] = False
    moving[:, WIDTH - shift - 2 :] = False
    moving[[0, -1], :] = moving[:, [0]] = False
    assert not auto_mask[moving].any()
    # Out-of-view pixels always take the identity error.
    assert auto_mask[:, WIDTH - shift + 1 :].all()


def test_masked_pixels_give_no_gradient():
    batch, depth, _ = static_patch_pair(2)
    depth = 1.3 * depth  # a little off, so that moving pixels have gradients

    def loss_of_inv_depth(inv_depth):
        return self_supervised_loss(
            pose_outputs(batch, [inv_depth]), batch, photometric.SelfSupervisedWeights(1.0, 0.0)
        )[0]

    gradient = np.asarray(jax.jit(jax.grad(loss_of_inv_depth))(jnp.asarray(1.0 / depth)))[0]
    _, terms = self_supervised_loss(pose_outputs(batch, [1.0 / depth]), batch)
    _, auto_mask = auto_mask_of(batch, depth)
    assert np.all(np.isfinite(gradient))
    np.testing.assert_allclose(float(terms["auto_mask_fraction"]), auto_mask.mean(), rtol=1e-6)
    # A pixel's depth moves its own warped value, which enters the SSIM windows of its
    # neighbours: pixels whose whole window takes the identity error get no gradient.
    window_masked = cv2.erode(auto_mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    window_masked[[0, -1], :] = window_masked[:, [0, -1]] = False  # reflection padding
    assert window_masked[10:14, 5:18].all()
    np.testing.assert_array_equal(gradient[window_masked], 0.0)
    assert np.abs(gradient[~auto_mask]).max() > 0


def test_loss_terms_weights_and_scales():
    batch, depth = shifted_pair(2)
    inv_depth = 1.0 / depth
    ramp = inv_depth * np.linspace(0.5, 1.5, WIDTH, dtype=np.float32)
    coarse = 2.0 * np.ones((1, HEIGHT // 2, WIDTH // 2), np.float32)
    weights = photometric.SelfSupervisedWeights(photometric=2.0, smoothness=0.5)
    loss, terms = self_supervised_loss(pose_outputs(batch, [ramp, coarse]), batch, weights)
    np.testing.assert_allclose(
        loss, 2.0 * terms["photometric"] + 0.5 * terms["smoothness"], rtol=1e-6
    )
    assert set(terms) == {
        "loss",
        "photometric",
        "smoothness",
        "auto_mask_fraction",
        "out_of_view_fraction",
    }
    # A constant coarse scale adds no smoothness; the fine ramp's mean-normalised
    # gradient is 1 / (W - 1) per column, weighted by the image edges, over 2 scales.
    _, fine_only = self_supervised_loss(pose_outputs(batch, [ramp]), batch)
    np.testing.assert_allclose(terms["smoothness"], fine_only["smoothness"] / 2, rtol=1e-5)
    assert 0 < float(fine_only["smoothness"]) <= 1.0 / (WIDTH - 1) + 1e-6
    # Scale-invariant: depth and translation scaled alike give the same loss.
    scaled = dict(batch, translation=3.0 * batch["translation"])
    _, scaled_terms = self_supervised_loss(
        pose_outputs(scaled, [ramp / 3.0, coarse / 3.0]), scaled, weights
    )
    np.testing.assert_allclose(scaled_terms["loss"], terms["loss"], rtol=1e-5)
    # Without intrinsics2 both views use intrinsics1 (equal here).
    one_camera = {key: value for key, value in batch.items() if key != "intrinsics2"}
    _, one_camera_terms = self_supervised_loss(pose_outputs(batch, [ramp]), one_camera)
    np.testing.assert_allclose(one_camera_terms["loss"], fine_only["loss"], rtol=1e-6)
    # Out of view at the true depth: the 2 columns whose lookup passes u = W - 0.5.
    _, true_terms = self_supervised_loss(pose_outputs(batch, [inv_depth]), batch)
    np.testing.assert_allclose(true_terms["out_of_view_fraction"], 2 / WIDTH, rtol=1e-5)


def test_bad_inputs_are_named():
    batch, depth = shifted_pair(2)
    outputs = pose_outputs(batch, [1.0 / depth])
    with pytest.raises(ValueError, match="rotation"):
        photometric.self_supervised_loss({"inv_depth_scales": outputs["inv_depth_scales"]}, batch)
    with pytest.raises(ValueError, match="intrinsics1"):
        photometric.self_supervised_loss(
            outputs, {k: v for k, v in batch.items() if k != "intrinsics1"}
        )
    with pytest.raises(ValueError, match=r"inv_depth_scales\[0\]"):
        photometric.self_supervised_loss(pose_outputs(batch, [1.0 / depth[:, :-1]]), batch)
    with pytest.raises(ValueError, match="smoothness"):
        photometric.SelfSupervisedWeights(smoothness=-1.0)
    with pytest.raises(ValueError, match="translation"):
        photometric.warp_to_view1(
            batch["image2"], depth, batch["rotation"], batch["translation"][:, :2], INTRINSICS[None]
        )


@pytest.mark.parametrize("augmentation", ["rotate_180", "mirror_x"])
def test_warp_commutes_with_the_pipelines_augmentation(augmentation):
    """Augmented intrinsics and pose describe the augmented images: warping then flipping
    equals flipping (images, depth, intrinsics, pose, by the input pipeline) then warping."""
    rng = np.random.default_rng(3)
    example = {
        "image1": texture(rng, HEIGHT, WIDTH),
        "image2": texture(rng, HEIGHT, WIDTH),
        "depth": rng.uniform(3.0, 6.0, (HEIGHT, WIDTH)).astype(np.float32),
        "intrinsics1": INTRINSICS,
        "intrinsics2": np.asarray([1.1, 0.9, 0.52, 0.4], np.float32),
        "rotation": geometry.rotation_matrix(np.asarray([0.02, -0.03, 0.05])).astype(np.float32),
        "translation": np.asarray([0.3, -0.2, 0.1], np.float32),
    }
    flipped = getattr(contract, augmentation)(example)

    def warp(example):
        warped, valid = warp_to_view1(
            jnp.asarray(example["image2"])[None],
            jnp.asarray(example["depth"])[None],
            jnp.asarray(example["rotation"])[None],
            jnp.asarray(example["translation"])[None],
            jnp.asarray(example["intrinsics1"])[None],
            jnp.asarray(example["intrinsics2"])[None],
        )
        return np.asarray(warped[0]), np.asarray(valid[0])

    warped, valid = warp(example)
    flip_axes = (0, 1) if augmentation == "rotate_180" else (1,)
    warped_flipped, valid_flipped = warp(flipped)
    assert 0.3 < valid.mean() < 1.0  # the pose moves part of view 1 out of image 2
    np.testing.assert_array_equal(valid_flipped, np.flip(valid, flip_axes))
    np.testing.assert_allclose(warped_flipped, np.flip(warped, flip_axes), atol=1e-4)


def test_optimisation_recovers_the_shift():
    """Adam on a free inverse-depth map (true pose) lowers the loss and moves the implied
    flow towards the true 2-pixel shift."""
    shift = 2
    batch, depth = shifted_pair(shift)
    fx_tx = float(INTRINSICS[0] * WIDTH * batch["translation"][0, 0])
    weights = photometric.SelfSupervisedWeights(photometric=1.0, smoothness=1e-2)

    def loss_fn(log_inv_depth):
        outputs = pose_outputs(batch, [jnp.exp(log_inv_depth)])
        return photometric.self_supervised_loss(outputs, batch, weights)[0]

    # Start at a 1-pixel flow: half the true inverse depth.
    log_inv_depth = jnp.log(jnp.asarray(0.5 / depth))
    optimizer = optax.adam(0.05)
    opt_state = optimizer.init(log_inv_depth)

    @jax.jit
    def step(log_inv_depth, opt_state):
        loss, grads = jax.value_and_grad(loss_fn)(log_inv_depth)
        updates, opt_state = optimizer.update(grads, opt_state)
        return optax.apply_updates(log_inv_depth, updates), opt_state, loss

    losses = []
    for _ in range(40):
        log_inv_depth, opt_state, loss = step(log_inv_depth, opt_state)
        losses.append(float(loss))
    implied_flow = fx_tx * np.exp(np.asarray(log_inv_depth))[0, 2:-2, 2 : WIDTH - shift - 2]
    assert losses[-1] < 0.5 * losses[0], losses
    assert abs(np.median(implied_flow) - shift) < 0.2, np.median(implied_flow)
