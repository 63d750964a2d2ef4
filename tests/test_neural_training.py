"""The learned residual's training step (``kernels.neural_training``, Warp's tile products; the tensor cores'
step in ``test_neural_tensor_cores.py``) against float64 NumPy: the device shuffle is a permutation of each epoch's
samples, the fused step's loss and gradients match central differences of the reference decoder (with and without
the highlights' inputs), Adam matches its float64 formula, and models trained side by side equal models trained
alone."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import reference
from warp_highlights.kernels import neural, neural_training
from warp_highlights.model.residual import NEURAL_HIDDEN, decoder_layer_shapes


def _problem(seed=0, lights=5, pixels=40, models=2):
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(lights, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    targets = rng.uniform(0.0, 1.0, (models, lights, pixels, 3)).astype(np.float32)
    return directions, targets


def highlight_decoder_reference(codes, weights, directions, luminance) -> np.ndarray:
    """(L, P, 3) float64: a decoder that sees the highlights, y = W3 elu(W2 elu(W1 elu(W0 [z, w, sqrt g, g] + b0) + b1)
    + b2) + b3, for (P, 9) codes at (L, 3) directions with (L, P) luminance g (display units, negative taken as 0)."""
    w0, b0, w1, b1, w2, b2, w3, b3 = (np.asarray(w, np.float64) for w in weights)
    codes = np.asarray(codes, np.float64)
    g = np.maximum(np.asarray(luminance, np.float64), 0.0)

    def elu(v):
        return np.where(v > 0, v, np.expm1(np.minimum(v, 0.0)))

    out = []
    for direction, row in zip(np.asarray(directions, np.float64).reshape(-1, 3), g):
        x = np.concatenate([codes, np.tile(direction, (len(codes), 1)), np.sqrt(row)[:, None], row[:, None]], axis=1).T
        out.append((w3 @ elu(w2 @ elu(w1 @ elu(w0 @ x + b0) + b1) + b2) + b3).T)
    return np.stack(out)


def seeing_decoder(pixels: int, seed: int = 0) -> neural.NeuralDecoder:
    """Random codes and a random decoder whose w0 has the highlights' two columns (weights about 1/sqrt(fan-in))."""
    rng = np.random.default_rng(seed)
    shapes = decoder_layer_shapes(NEURAL_HIDDEN, highlights=True)
    weights = [rng.normal(0.0, 1.0 / np.sqrt(shape[1]), shape).astype(np.float32) for shape in shapes]
    return neural.NeuralDecoder(rng.normal(size=(pixels, neural.CODE_SIZE)).astype(np.float32), weights)


@wp.kernel
def _shuffle_all(total: wp.int64, key: int, half_bits: int, out: wp.array[wp.int64]):
    i = wp.tid()
    out[i] = neural_training.shuffled_sample(wp.int64(i), total, key, half_bits)


@pytest.mark.parametrize("total", [1, 2, 7, 64, 1000, 4097])
def test_the_shuffle_is_a_permutation_of_every_epoch(device, total):
    """Each key orders [0, total) anew, every sample exactly once (brute force over all positions)."""
    half_bits = neural_training._feistel_half_bits(total)
    assert 4**half_bits >= total
    orders = []
    for key in (0, 1, 977):
        out = wp.zeros(total, dtype=wp.int64, device=device)
        wp.launch(_shuffle_all, dim=total, inputs=[total, key, half_bits], outputs=[out], device=device)
        order = out.numpy()
        np.testing.assert_array_equal(np.sort(order), np.arange(total))
        orders.append(order)
    if total >= 64:  # shuffled, and differently for each key
        assert not np.array_equal(orders[0], np.arange(total)) and not np.array_equal(orders[0], orders[1])


def _one_step_gradients(trainer):
    """A step's launches up to Adam: the step's samples, loss and gradients."""
    for name, launch in trainer.launches():
        if name == "adam_flat":
            break
        launch()
    return trainer.samples.numpy(), trainer.loss.numpy()[:, 0], trainer.step_gradients()


def test_the_fused_step_gradients_match_central_differences(device):
    """Two models, a batch that runs into the second epoch (repeated samples), lights 1 and 3 left out: the
    step's loss is the mean squared error over its samples and every gradient (codes and the eight weight
    arrays) that of the float64 reference decoder."""
    directions, targets = _problem(seed=1)
    used = np.array([0, 2, 4])
    models = [neural.initial_model(targets[m][used], seed=m + 2) for m in range(2)]
    trainer = neural_training.DecoderTrainer(targets, directions, used, models, 150, 10, device=device,
                                             tile=(32, 3, 32), tensor_cores=False)  # 2 blocks of 3 tiles
    assert trainer.batch == 192 and trainer.blocks == 2 and trainer.total == 120
    samples, loss, gradients = _one_step_gradients(trainer)
    light, pixel = samples // 40, samples % 40
    assert set(light) <= set(used) and len(np.unique(samples)) == 120  # the first epoch whole, then the second's start
    rng = np.random.default_rng(0)
    for m in range(2):
        params = [models[m].codes.astype(np.float64)] + [w.astype(np.float64) for w in models[m].weights]

        def mse(values, m=m):
            decoded = reference.neural_decoder(values[0], values[1:], directions)
            return np.sum((decoded[light, pixel] - targets[m][light, pixel]) ** 2) / len(samples)

        assert loss[m] == pytest.approx(mse(params), rel=1e-5)
        for which in range(len(params)):
            gradient = gradients[which][m]
            for _ in range(3):
                index = tuple(int(rng.integers(0, s)) for s in params[which].shape)
                if which == 0:
                    index = (int(pixel[rng.integers(len(pixel))]), index[1])  # a pixel the step saw
                plus = [p.copy() for p in params]
                minus = [p.copy() for p in params]
                plus[which][index] += 1e-4
                minus[which][index] -= 1e-4
                numeric = (mse(plus) - mse(minus)) / 2e-4
                assert gradient[index] == pytest.approx(numeric, rel=2e-3, abs=2e-6), (m, which, index)
        unseen = np.setdiff1d(np.arange(40), pixel)
        assert np.all(gradients[0][m][unseen] == 0.0)


def test_the_fused_step_gradients_of_a_model_that_sees_the_highlights_match_central_differences(device):
    """A model that sees the highlights beside one that does not, in the same launches: the seeing model's loss and
    gradients (codes, the eight weight arrays, w0's two highlight columns in full) those of the float64 reference
    with [code, direction, sqrt(g), g] inputs; the other's highlight columns get no gradient and it matches the
    reference without highlights."""
    directions, targets = _problem(seed=2)
    g = np.random.default_rng(3).uniform(-0.3, 2.0, (5, 40)).astype(np.float32)
    seeing = seeing_decoder(40, seed=5)
    models = [seeing, neural.initial_model(targets[1], seed=3)]
    trainer = neural_training.DecoderTrainer(targets, directions, np.arange(5), models, 150, 10, device=device,
                                             tile=(32, 3, 32), highlights=g, sees=(True, False),
                                             tensor_cores=False)
    samples, loss, gradients = _one_step_gradients(trainer)
    light, pixel = samples // 40, samples % 40
    rng = np.random.default_rng(0)
    for m in range(2):
        params = [models[m].codes.astype(np.float64)] + [w.astype(np.float64) for w in models[m].weights]

        def mse(values, m=m):
            if m == 0:
                decoded = highlight_decoder_reference(values[0], values[1:], directions, g)
            else:
                decoded = reference.neural_decoder(values[0], values[1:], directions)
            return np.sum((decoded[light, pixel] - targets[m][light, pixel]) ** 2) / len(samples)

        assert loss[m] == pytest.approx(mse(params), rel=1e-5)
        checked = []
        for which in range(len(params)):
            indices = []
            for _ in range(3):
                index = tuple(int(rng.integers(0, s)) for s in params[which].shape)
                if which == 0:
                    index = (int(pixel[rng.integers(len(pixel))]), index[1])  # a pixel the step saw
                indices.append(index)
            if which == 1 and m == 0:  # every unit's weights of sqrt(g) and g
                indices += [(row, column) for row in range(neural.HIDDEN) for column in (12, 13)]
            checked.append(len(indices))
            for index in indices:
                plus = [p.copy() for p in params]
                minus = [p.copy() for p in params]
                plus[which][index] += 1e-4
                minus[which][index] -= 1e-4
                numeric = (mse(plus) - mse(minus)) / 2e-4
                assert gradients[which][m][index] == pytest.approx(numeric, rel=2e-3, abs=2e-6), (m, which, index)
        assert gradients[1].shape[2] == neural.INPUTS
    assert np.any(gradients[1][0][:, 12:] != 0.0) and not np.any(gradients[1][1][:, 12:])
    result = trainer.result()
    assert result[0].weights[0].shape == (neural.HIDDEN, 14) and result[1].weights[0].shape == (neural.HIDDEN, 12)


def _highlight_problem(seed=0, lights=24, pixels=64):
    """Targets that are a function of the Gaussians' luminance g alone, g drawn anew for every light and pixel: the
    direction and the pixel's code cannot predict them, g can."""
    rng = np.random.default_rng(seed)
    directions = rng.normal(size=(lights, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    g = rng.uniform(0.0, 1.0, (lights, pixels)).astype(np.float32)
    one = np.stack([g, 1.0 - g, np.sqrt(g)], axis=-1).astype(np.float32)
    return directions, np.stack([one, one]), g


def test_a_model_that_sees_informative_highlights_learns_what_one_that_does_not_cannot(device):
    """Two models side by side on 16 of 24 lights, the first seeing the highlights: its w0 comes back with 14
    columns, the other's with 12; on targets only g predicts, the seeing one ends far below the other, at the lights
    it learned and at the 8 left out, and each ends as it would learn alone."""
    directions, targets, g = _highlight_problem()
    used, left_out = np.arange(16), np.arange(16, 24)
    options = dict(device=device, epochs=30, batch=64, lr=1e-2, final_lr=1e-3, used=used)
    models, history = neural_training.train_decoders(targets, directions, highlights=g, sees=[True, False],
                                                     **options)
    assert history.shape == (30, 2) and np.all(np.isfinite(history))
    assert models[0].weights[0].shape == (neural.HIDDEN, 14) and models[1].weights[0].shape == (neural.HIDDEN, 12)
    assert history[-1, 0] < 0.1 * history[-1, 1]
    errors = [np.mean(np.sum((decoded - targets[0][left_out]) ** 2, axis=-1))
              for decoded in (neural.decode(models[0], directions[left_out], device=device, highlights=g[left_out]),
                              neural.decode(models[1], directions[left_out], device=device))]
    assert errors[0] < 0.1 * errors[1]
    seeing, seeing_history = neural_training.train_decoder(targets[0], directions, highlights=g, **options)
    blind, blind_history = neural_training.train_decoder(targets[1], directions, **options)
    for together, alone in ((models[0], seeing), (models[1], blind)):
        np.testing.assert_allclose(together.codes, alone.codes, rtol=1e-4, atol=1e-5)
        for got, want in zip(together.weights, alone.weights):
            assert got.shape == want.shape
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(history[:, 0], seeing_history, rtol=1e-4)
    np.testing.assert_allclose(history[:, 1], blind_history, rtol=1e-4)


def test_a_model_that_sees_the_highlights_may_start_from_one_that_does_not(device):
    """An initial decoder of 12 columns goes on with zero weights for the highlights' inputs (its first step's loss
    is its own); it is settled on and goes on alone as it would have; 14 columns are for seeing models only, and
    a seeing model needs the highlights."""
    directions, targets, g = _highlight_problem(seed=1, lights=6, pixels=48)
    options = dict(device=device, epochs=3, batch=64)
    start, _ = neural_training.train_decoder(targets[1], directions, **options)
    trainer = neural_training.DecoderTrainer(targets[:1], directions, np.arange(6), [start], 64, 3, device=device,
                                             highlights=g)
    _, loss, _ = _one_step_gradients(trainer)
    samples = trainer.samples.numpy()
    decoded = reference.neural_decoder(start.codes, start.weights, directions)
    light, pixel = samples // 48, samples % 48
    want = np.sum((decoded[light, pixel] - targets[0][light, pixel]) ** 2) / len(samples)
    assert loss[0] == pytest.approx(want, rel=1e-5)
    kept, _ = neural_training.train_decoders(targets, directions, initial=[start, start], highlights=g,
                                             sees=[False, True], settle=lambda models: 1, settle_epoch=1, **options)
    alone, _ = neural_training.train_decoder(targets[1], directions, initial=start, highlights=g, **options)
    assert kept[1].weights[0].shape == alone.weights[0].shape == (neural.HIDDEN, 14)
    assert kept[0].weights[0].shape == (neural.HIDDEN, 12)
    np.testing.assert_allclose(kept[1].codes, alone.codes, rtol=1e-4, atol=1e-5)
    for got, want in zip(kept[1].weights, alone.weights):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="does not see"):
        neural_training.train_decoders(targets, directions, initial=[alone, start], highlights=g, sees=[False, True],
                                       **options)
    with pytest.raises(ValueError, match="pass highlights"):
        neural_training.train_decoders(targets, directions, sees=[True, False], **options)
    with pytest.raises(ValueError, match="highlights must be"):
        neural_training.train_decoders(targets, directions, highlights=g[:, :10], **options)


def test_the_weights_gradients_are_the_same_in_every_run(device):
    """Eight blocks' partial sums added in block order: two runs of a step give the weights' gradients bit for
    bit (atomic adds on a GPU would sum them in any order)."""
    directions, targets = _problem(seed=4, pixels=400)
    models = [neural.initial_model(targets[m], seed=m) for m in range(2)]
    runs = []
    for _ in range(2):
        trainer = neural_training.DecoderTrainer(targets, directions, np.arange(5), models, 1024, 10, device=device,
                                                 tile=(32, 4, 32), tensor_cores=False)
        assert trainer.blocks == 8
        runs.append(_one_step_gradients(trainer)[2][1:])
    for first, second in zip(*runs):
        assert np.any(first != 0.0)
        np.testing.assert_array_equal(first, second)


def test_adam_matches_its_formula(device):
    """A step's Adam, one flat launch: a weight's gradient is its blocks' partial sums added to the gradient buffer;
    the moments, the bias corrections of step t, each parameter's learning rate at the epoch of step t - 1 (from its
    own first rate); the gradient zeroed; the step counter set to t."""
    rng = np.random.default_rng(3)
    params, grads = rng.normal(size=50), rng.normal(size=50)
    first, second = rng.normal(size=50) * 0.1, rng.uniform(0.0, 0.1, 50)
    grads[20:] = 0.0  # the weights' entries: only their partial sums
    partials = rng.normal(size=(3, 30))  # three blocks' sums of the last 30 parameters' gradients
    arrays = [wp.array(a.astype(np.float32), dtype=float, device=device) for a in (params, grads, first, second)]
    adam_step = wp.array(np.array([8], np.int64), dtype=wp.int64, device=device)
    step = wp.array(np.array([7], np.int64), dtype=wp.int64, device=device)
    batch, total, epochs, final_lr = 64, 100, 10, 3e-4
    lr = np.where(np.arange(50) < 20, 3e-3, 1e-2)
    partial_array = wp.array(partials.astype(np.float32), dtype=float, device=device)
    wp.launch(neural_training.adam_flat, dim=50,
              inputs=[adam_step, batch, total, epochs, partial_array, 20,
                      wp.array(np.log(lr).astype(np.float32), dtype=float, device=device), np.log(final_lr)],
              outputs=[*arrays, step], device=device)
    assert step.numpy()[0] == 8
    grads = grads + np.concatenate([np.zeros(20), partials.sum(axis=0)])
    epoch = 7 * 64 // 100
    rate = lr * (final_lr / lr) ** (epoch / (epochs - 1))
    m = 0.9 * first + 0.1 * grads
    v = 0.999 * second + 0.001 * grads**2
    want = params - rate * (m / (1 - 0.9**8)) / (np.sqrt(v / (1 - 0.999**8)) + 1e-8)
    np.testing.assert_allclose(arrays[0].numpy(), want, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(arrays[2].numpy(), m, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(arrays[3].numpy(), v, rtol=1e-4, atol=1e-9)
    assert not arrays[1].numpy().any()


def test_models_side_by_side_learn_as_each_alone(device):
    """Two models in the same launches see the same samples and end as each would trained on its own."""
    directions, targets = _problem(seed=4, lights=4, pixels=48)
    together, history = neural_training.train_decoders(targets, directions, device=device, epochs=3, batch=64)
    assert history.shape == (3, 2) and np.all(np.isfinite(history))
    for m in range(2):
        alone, alone_history = neural_training.train_decoder(targets[m], directions, device=device, epochs=3, batch=64)
        np.testing.assert_allclose(together[m].codes, alone.codes, rtol=1e-4, atol=1e-5)
        for got, want in zip(together[m].weights, alone.weights):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(history[:, m], alone_history, rtol=1e-4)
    with pytest.raises(ValueError, match="initial models"):
        neural_training.train_decoders(targets, directions, device=device, epochs=1, initial=together[:1])


def test_models_side_by_side_each_learn_at_their_own_rate(device):
    """Two models from two first learning rates in the same launches end as each would alone at its rate, and a
    settled winner goes on at its own rate."""
    directions, targets = _problem(seed=11, lights=4, pixels=48)
    rates = (3e-3, 1e-2)
    together, _ = neural_training.train_decoders(targets, directions, device=device, epochs=3, batch=64, lr=rates)
    kept, _ = neural_training.train_decoders(targets, directions, device=device, epochs=3, batch=64, lr=rates,
                                             settle=lambda models: 1, settle_epoch=1)
    for m, rate in enumerate(rates):
        alone, _ = neural_training.train_decoder(targets[m], directions, device=device, epochs=3, batch=64, lr=rate)
        np.testing.assert_allclose(together[m].codes, alone.codes, rtol=1e-4, atol=1e-5)
        for got, want in zip(together[m].weights, alone.weights):
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(kept[1].codes, together[1].codes, rtol=1e-4, atol=1e-5)
    assert not np.allclose(together[0].codes, together[1].codes, atol=1e-3)
    with pytest.raises(ValueError, match="learning rates"):
        neural_training.train_decoders(targets, directions, device=device, epochs=1, lr=(3e-3, 0.0))


def _keeping_second():
    """A ``settle`` that keeps model 1 the first time it is asked, and the list of the models it was shown."""
    seen = []

    def keep_second(models):
        seen.append(models)
        return 1

    return seen, keep_second


def test_a_settled_order_stops_the_loser_and_the_winner_goes_on_as_alone(device):
    """``settle`` keeps model 1 after the first of three epochs: model 0 is returned as it was then (its loss NaN
    afterwards), model 1 ends as if it had learned alone all along (parameters, Adam's moments and the step carried
    over); None keeps both."""
    directions, targets = _problem(seed=7, lights=4, pixels=48)
    seen, keep_second = _keeping_second()
    models, history = neural_training.train_decoders(targets, directions, device=device, epochs=3, batch=64,
                                                     settle=keep_second, settle_epoch=1)
    assert len(seen) == 1 and np.isnan(history[1:, 0]).all() and np.isfinite(history[:, 1]).all()
    np.testing.assert_array_equal(models[0].codes, seen[0][0].codes)
    alone, alone_history = neural_training.train_decoder(targets[1], directions, device=device, epochs=3, batch=64)
    np.testing.assert_allclose(models[1].codes, alone.codes, rtol=1e-4, atol=1e-5)
    for got, want in zip(models[1].weights, alone.weights):
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(history[:, 1], alone_history, rtol=1e-4)
    both, both_history = neural_training.train_decoders(targets, directions, device=device, epochs=3, batch=64,
                                                        settle=lambda models: None, settle_epoch=1)
    assert np.isfinite(both_history).all()
    np.testing.assert_allclose(both[1].codes, alone.codes, rtol=1e-4, atol=1e-5)


def test_a_settled_order_stops_every_model_where_asked(device):
    """``stop_when_settled``: once ``settle`` names a model, every model stops there, returned as they were (the
    check of a field that learns anew keeps neither); an unsettled order goes on as without it."""
    directions, targets = _problem(seed=7, lights=4, pixels=48)
    seen, keep_second = _keeping_second()
    models, history = neural_training.train_decoders(targets, directions, device=device, epochs=3, batch=64,
                                                     settle=keep_second, settle_epoch=1, stop_when_settled=True)
    assert len(seen) == 1 and history.shape == (1, 2) and np.isfinite(history).all()
    for model, then in zip(models, seen[0]):
        np.testing.assert_array_equal(model.codes, then.codes)
    first, _ = neural_training.train_decoders(targets, directions, device=device, epochs=1, batch=64)
    for model, want in zip(models, first):
        np.testing.assert_allclose(model.codes, want.codes, rtol=1e-4, atol=1e-5)
    _, unsettled = neural_training.train_decoders(targets, directions, device=device, epochs=3, batch=64,
                                                  settle=lambda models: None, settle_epoch=1, stop_when_settled=True)
    assert unsettled.shape == (3, 2) and np.isfinite(unsettled).all()


def test_an_order_not_settled_is_asked_again_after_each_settle_epoch(device):
    """``settle`` returning None leaves both models learning and is asked again ``settle_epoch`` epochs later; once it
    names a model the other stops there and it is not asked again."""
    directions, targets = _problem(seed=6, lights=4, pixels=48)
    asked = []

    def second_time(models):
        asked.append(len(asked))
        return None if len(asked) == 1 else 0

    _, history = neural_training.train_decoders(targets, directions, device=device, epochs=5, batch=64,
                                                settle=second_time, settle_epoch=1)
    assert asked == [0, 1]
    assert np.isfinite(history[:2, 1]).all() and np.isnan(history[2:, 1]).all() and np.isfinite(history[:, 0]).all()


def test_the_settle_scoring_is_not_training_time(device):
    """``seconds`` counts training only: a ``settle`` that takes longer than the whole budget (on a fresh machine
    its scoring compiles the decoding kernels) leaves the winner its epochs."""
    import time

    directions, targets = _problem(seed=5, lights=4, pixels=48)

    def slow_settle(models):
        time.sleep(1.5)
        return 1

    _, history = neural_training.train_decoders(targets, directions, device=device, epochs=6, batch=64, seconds=1.0,
                                                settle=slow_settle, settle_epoch=2)
    assert len(history) == 6 and np.isfinite(history[:, 1]).all()


def test_the_kept_model_can_go_on_with_more_lights_at_the_same_point_of_its_schedule(device):
    """``settle_used``: after settling, the winner learns every light. Its step counter lands on the same epoch
    of the larger sample count (the learning rate goes on from where it was), and it learns the lights it had
    never seen: on them it ends far closer than the model kept on its first lights."""
    directions, targets = _problem(seed=9, lights=5, pixels=512)
    used = np.array([0, 1, 2])
    trainer = neural_training.DecoderTrainer(targets, directions, used, [neural_training.initial_model(t[used])
                                                                          for t in targets], 512, 4, device=device)
    trainer.steps(2 * trainer.steps_per_epoch)
    alone = trainer.keep(1, used=np.arange(5))
    assert int(alone.step.numpy()[0]) == 2 * alone.steps_per_epoch and alone.steps_per_epoch > trainer.steps_per_epoch
    kwargs = dict(device=device, epochs=24, batch=512, used=used, settle=lambda models: 1, settle_epoch=2)
    narrow, _ = neural_training.train_decoders(targets, directions, **kwargs)
    wide, history = neural_training.train_decoders(targets, directions, settle_used=np.arange(5), **kwargs)
    assert np.isfinite(history[:, 1]).all()
    from warp_highlights.residual.cpu_training import decode_cpu

    errors = [float(np.mean((decode_cpu(m[1].codes, m[1].weights, directions[3:]) - targets[1, 3:]) ** 2))
              for m in (narrow, wide)]
    assert errors[1] < 0.8 * errors[0]


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA device")
def test_a_model_trained_on_cuda_decodes_the_same_on_the_cpu():
    """The trained decoder, decoded by Warp on CUDA and on the CPU and by the float64 reference, agrees within float
    tolerance; the CUDA training step's gradients were checked above with the other devices."""
    directions, targets = _problem(seed=8, lights=6, pixels=256, models=1)
    model, _ = neural_training.train_decoder(targets[0], directions, device="cuda:0", epochs=5, batch=512)
    on_cuda = neural.decode(model, directions, device="cuda:0")
    on_cpu = neural.decode(model, directions, device="cpu")
    np.testing.assert_allclose(on_cuda, on_cpu, rtol=1e-4, atol=2e-5)
    np.testing.assert_allclose(on_cpu, reference.neural_decoder(model.codes, model.weights, directions), rtol=1e-4,
                               atol=2e-5)
