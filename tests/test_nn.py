"""Rotation heads (``diffquat.torch.nn`` and ``diffquat.jax.nn``): every representation maps any raw
output to a rotation, agrees with an independent NumPy/scipy oracle, has finite-difference-correct
gradients, traces, and the torch layer and the jax pure functions have the same parameters and shapes."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import torch
from cases import only
from conftest import Backend
from flax import nnx
from scipy.spatial.transform import Rotation

import diffquat.jax as dq
import diffquat.jax.nn as jnn
import diffquat.torch.nn as tnn

heads = only(backend=lambda b: b in ("torch", "jax"))
REPRESENTATIONS = ("quaternion", "axis_angle", "euler", "6d", "9d", "10d", "fisher")
SIZES = {"quaternion": 4, "axis_angle": 3, "euler": 3, "6d": 6, "9d": 9, "10d": 10, "fisher": 9}


def gram_schmidt(raw: np.ndarray) -> np.ndarray:
    a1, a2 = raw[..., :3], raw[..., 3:]
    b1 = a1 / np.linalg.norm(a1, axis=-1, keepdims=True)
    a2 = a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1
    b2 = a2 / np.linalg.norm(a2, axis=-1, keepdims=True)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=-1)  # the two vectors are the first two *columns*


def svd_projection(raw: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(raw.reshape(*raw.shape[:-1], 3, 3))
    d = np.ones((*raw.shape[:-1], 3))
    d[..., 2] = np.sign(np.linalg.det(u @ vt))
    return (u * d[..., None, :]) @ vt


def smallest_eigenvector_rotation(raw: np.ndarray) -> np.ndarray:
    rows, cols = np.triu_indices(4)
    a = np.zeros((*raw.shape[:-1], 4, 4))
    a[..., rows, cols] = raw
    a[..., cols, rows] = raw
    q = np.linalg.eigh(a)[1][..., :, 0]
    return Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).as_matrix().reshape(*raw.shape[:-1], 3, 3)


def flat_scipy(make: Callable[[np.ndarray], Rotation], trailing: int) -> Callable[[np.ndarray], np.ndarray]:
    return lambda raw: make(raw.reshape(-1, trailing)).as_matrix().reshape(*raw.shape[:-1], 3, 3)


ORACLES: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "quaternion": flat_scipy(lambda r: Rotation.from_quat(r, scalar_first=True), 4),
    "axis_angle": flat_scipy(Rotation.from_rotvec, 3),
    "euler": flat_scipy(lambda r: Rotation.from_euler("XYZ", r), 3),
    "6d": gram_schmidt,
    "9d": svd_projection,
    "10d": smallest_eigenvector_rotation,
    "fisher": svd_projection,  # the mode of the matrix Fisher distribution of F = raw (row-major)
}


def raw_outputs(representation: str, batch: tuple[int, ...] = (4, 3), seed: int = 0) -> np.ndarray:
    """What an untrained network emits: Gaussian raw outputs (float64)."""
    return np.random.default_rng(seed).normal(size=(*batch, SIZES[representation]))


def to_matrix(backend: Backend, raw: np.ndarray, representation: str) -> np.ndarray:
    nn = tnn if backend.name == "torch" else jnn
    return backend.to_numpy(nn.representation_to_matrix(backend.array(raw, "float64"), representation))


def test_every_representation_is_tested_and_exported_by_both_backends() -> None:
    assert tnn.REPRESENTATIONS == jnn.REPRESENTATIONS == REPRESENTATIONS
    for r in REPRESENTATIONS:
        assert tnn.representation_size(r) == jnn.representation_size(r) == SIZES[r]


@heads
@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_head_gives_the_oracle_rotation(backend: Backend, representation: str) -> None:
    raw = raw_outputs(representation)
    out = to_matrix(backend, raw, representation)
    assert out.shape == (4, 3, 3, 3)
    np.testing.assert_allclose(out, ORACLES[representation](raw), atol=1e-10)
    np.testing.assert_allclose(out.swapaxes(-1, -2) @ out, np.broadcast_to(np.eye(3), out.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(out), 1.0, atol=1e-12)


@heads
@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_head_gradient_matches_finite_differences(backend: Backend, representation: str) -> None:
    raw = raw_outputs(representation, batch=(3,), seed=1)
    weights = np.random.default_rng(2).normal(size=(3, 3, 3))  # a generic scalar loss of R

    if backend.name == "torch":
        x = torch.tensor(raw, requires_grad=True)
        (tnn.representation_to_matrix(x, representation) * torch.tensor(weights)).sum().backward()
        assert x.grad is not None
        grad = x.grad.numpy()
    else:
        fn = lambda x: jnp.sum(jnn.representation_to_matrix(x, representation) * jnp.asarray(weights))  # noqa: E731
        grad = np.asarray(jax.grad(fn)(jnp.asarray(raw)))
    # Central differences, every perturbation evaluated in one batched call (a leading batch axis).
    h = 1e-6
    steps = h * np.eye(raw.size).reshape(raw.size, *raw.shape)
    batched = np.concatenate([raw + steps, raw - steps])
    losses = np.sum(to_matrix(backend, batched, representation) * weights, axis=(-3, -2, -1))
    fd = ((losses[: raw.size] - losses[raw.size :]) / (2 * h)).reshape(raw.shape)
    np.testing.assert_allclose(grad, fd, atol=1e-6)


@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_jax_head_traces_under_jit_and_vmap(representation: str) -> None:
    raw = jnp.asarray(raw_outputs(representation))
    eager = jnn.representation_to_matrix(raw, representation)
    jitted = jax.jit(jnn.representation_to_matrix, static_argnums=1)(raw, representation)
    mapped = jax.vmap(lambda r: jnn.representation_to_matrix(r, representation))(raw)
    np.testing.assert_allclose(jitted, eager, atol=1e-12)
    np.testing.assert_allclose(mapped, eager, atol=1e-12)


@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_torch_head_runs_under_torch_func_vmap(representation: str) -> None:
    raw = torch.tensor(raw_outputs(representation))
    mapped = torch.func.vmap(lambda r: tnn.representation_to_matrix(r, representation))(raw)
    torch.testing.assert_close(mapped, tnn.representation_to_matrix(raw, representation))


@pytest.mark.parametrize("representation", REPRESENTATIONS)
def test_torch_layer_and_jax_functions_have_the_same_parameters(representation: str) -> None:
    layer = tnn.RotationHead(7, representation=representation, dtype=torch.float64)
    params = jnn.init_rotation_head(jax.random.key(0), 7, representation)
    n = SIZES[representation]
    assert layer.linear.weight.shape == (n, 7) and params["w"].shape == (7, n)
    assert layer.linear.bias is not None and layer.linear.bias.shape == params["b"].shape == (n,)
    # The same initialisation bounds as torch.nn.Linear (uniform in +-1/sqrt(in_features)).
    assert float(jnp.max(jnp.abs(params["w"]))) <= 1 / np.sqrt(7)
    # The same weights give the same matrices on both backends.
    features = np.random.default_rng(3).normal(size=(2, 5, 7))
    with torch.no_grad():
        layer.linear.weight.copy_(torch.tensor(np.asarray(params["w"]).T))
        layer.linear.bias.copy_(torch.tensor(np.asarray(params["b"])))
        ours = layer(torch.tensor(features)).numpy()
    theirs = np.asarray(jnn.rotation_head(params, jnp.asarray(features), representation))
    assert ours.shape == (2, 5, 3, 3)
    np.testing.assert_allclose(ours, theirs, atol=1e-12)
    assert repr(representation) in repr(layer)


def test_torch_layer_trains_its_parameters() -> None:
    layer = tnn.RotationHead(5, "6d", dtype=torch.float64)
    layer(torch.randn(4, 5, dtype=torch.float64)).sum().backward()
    for p in layer.parameters():
        assert p.grad is not None and bool(torch.all(torch.isfinite(p.grad))) and bool(torch.any(p.grad != 0))


def test_torch_head_saves_its_representation_and_refuses_another(tmp_path: Any) -> None:
    """The representation travels in the state_dict (through torch.save and a weights-only load): a
    head of the same representation loads the weights and gives the same rotations; one of another
    representation refuses them, naming both, even where the shapes agree (axis-angle and Euler both
    have 3 raw outputs) and before torch reports a size mismatch (quaternion: 4 raw outputs)."""
    torch.manual_seed(0)
    saved = tnn.RotationHead(5, "axis_angle", dtype=torch.float64)
    code = saved.state_dict()["representation_code"]
    assert bytes(code.tolist()).rstrip(b"\0") == b"axis_angle"
    torch.save(saved.state_dict(), tmp_path / "head.pt")
    state = torch.load(tmp_path / "head.pt", weights_only=True)
    loaded = tnn.RotationHead(5, "axis_angle", dtype=torch.float64)
    loaded.load_state_dict(state)
    x = torch.randn(3, 5, dtype=torch.float64)
    torch.testing.assert_close(loaded(x), saved(x), rtol=0, atol=0)
    for other in ("euler", "quaternion"):
        head = tnn.RotationHead(5, other, dtype=torch.float64)
        expected = rf"RotationHead: .* saved for representation 'axis_angle', this head's is '{other}'"
        with pytest.raises(ValueError, match=expected):
            head.load_state_dict(state)


def test_torch_head_documents_its_forward() -> None:
    doc = tnn.RotationHead.forward.__doc__ or ""
    assert "(..., 3, 3)" in doc and "(..., in_features)" in doc


@heads
def test_unknown_representation_and_wrong_size_raise(backend: Backend) -> None:
    nn = tnn if backend.name == "torch" else jnn
    with pytest.raises(ValueError, match=r"unknown rotation representation 'rot6d'.*'6d'"):
        nn.representation_size("rot6d")
    with pytest.raises(ValueError, match=r"expected raw of shape \(\.\.\., 6\).*'6d', got shape \(2, 9\)"):
        nn.representation_to_matrix(backend.array(np.zeros((2, 9)), "float64"), "6d")


def _flax_model(in_features: int, representation: str) -> tuple[Callable, Any, dict[str, Any]]:
    """A two-layer flax (nnx) model ending in the rotation map; returns (apply(state, x), state, the
    last layer's parameters as ``rotation_head`` takes them)."""

    class Model(nnx.Module):
        def __init__(self, rngs: nnx.Rngs) -> None:
            self.hidden = nnx.Linear(in_features, 16, rngs=rngs, param_dtype=jnp.float64)
            self.out = nnx.Linear(
                16, jnn.representation_size(representation), rngs=rngs, param_dtype=jnp.float64
            )

        def features(self, x: Any) -> Any:
            return jax.nn.tanh(self.hidden(x))

        def __call__(self, x: Any) -> Any:
            return jnn.representation_to_matrix(self.out(self.features(x)), representation)

    graphdef, state = nnx.split(Model(nnx.Rngs(0)))

    def apply(state: Any, x: Any) -> Any:
        return nnx.merge(graphdef, state)(x)

    def head_params(state: Any, x: Any) -> tuple[dict[str, Any], Any]:
        model = nnx.merge(graphdef, state)
        return {"w": model.out.kernel[...], "b": model.out.bias[...]}, model.features(x)

    return apply, state, head_params


def _equinox_model(in_features: int, representation: str) -> tuple[Callable, Any, Callable]:
    class Model(eqx.Module):
        hidden: eqx.nn.Linear
        out: eqx.nn.Linear

        def __init__(self, key: Any) -> None:
            k1, k2 = jax.random.split(key)
            self.hidden = eqx.nn.Linear(in_features, 16, key=k1, dtype=jnp.float64)
            self.out = eqx.nn.Linear(16, jnn.representation_size(representation), key=k2, dtype=jnp.float64)

        def features(self, x: Any) -> Any:
            return jax.nn.tanh(jax.vmap(self.hidden)(x))

        def __call__(self, x: Any) -> Any:
            # equinox layers act on one example: vmap over the batch, then the batched rotation map
            return jnn.representation_to_matrix(jax.vmap(self.out)(self.features(x)), representation)

    def apply(model: Any, x: Any) -> Any:
        return model(x)

    def head_params(model: Any, x: Any) -> tuple[dict[str, Any], Any]:
        return {"w": model.out.weight.T, "b": model.out.bias}, model.features(x)

    return apply, Model(jax.random.key(0)), head_params


@pytest.mark.parametrize("representation", ["6d", "9d", "10d", "fisher"])
@pytest.mark.parametrize("framework", ["flax", "equinox"])
def test_jax_heads_train_inside_flax_and_equinox_models(framework: str, representation: str) -> None:
    """The jax heads are plain functions, so they sit at the end of a flax or equinox model: the model
    equals ``rotation_head`` on its own last layer's parameters, and optax trains it through
    ``jax.jit`` with a geodesic loss (the loss falls, the gradients are finite)."""
    make = _flax_model if framework == "flax" else _equinox_model
    apply, params, head_params = make(5, representation)
    rng = np.random.default_rng(4)
    x = jnp.asarray(rng.normal(size=(32, 5)))
    target = jnp.asarray(Rotation.random(32, random_state=5).as_matrix())

    # Compiled, as such models run: eagerly, every flax, equinox and diffquat operation compiled on
    # its own first, which was most of this test's time.
    @jax.jit
    def model_and_head(params: Any) -> tuple[Any, Any]:
        head, features = head_params(params, x)
        return apply(params, x), jnn.rotation_head(head, features, representation)

    np.testing.assert_allclose(*model_and_head(params), atol=1e-12)

    @jax.jit
    def loss(params: Any) -> Any:
        return dq.matrix_geodesic_distance(apply(params, x), target).mean()

    optimizer = optax.adam(3e-2)

    @jax.jit
    def step(params: Any, opt_state: Any) -> tuple[Any, Any, Any]:
        value, grads = jax.value_and_grad(loss)(params)
        # optax's bias correction mixes Python floats and int32 step counts (the suite runs jax with
        # strict dtype promotion to keep diffquat's own code clean of implicit promotions)
        with jax.numpy_dtype_promotion("standard"):
            updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, (value, grads)

    opt_state = optimizer.init(params)
    first = float(loss(params))
    for _ in range(60):
        params, opt_state, (_, grads) = step(params, opt_state)
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grads))
    assert float(loss(params)) < 0.5 * first


@heads
def test_fisher_head_trains_by_its_negative_log_likelihood(backend: Backend) -> None:
    """A ``"fisher"`` head's F is its raw output (row-major), its rotation the distribution's mode; a
    linear head trained by the matrix Fisher NLL (torch: Adam on ``RotationHead.fisher``; jax: optax on
    ``representation_to_fisher``) lowers the NLL and the geodesic error of its mode, with finite
    gradients. Other heads have no F."""
    rng = np.random.default_rng(7)
    x = rng.normal(size=(64, 5))
    target = (
        Rotation.random(1, random_state=8).as_matrix()[0]
        @ Rotation.from_rotvec(0.1 * rng.normal(size=(64, 3))).as_matrix()
    )  # a concentrated cloud: the NLL can learn both where and how sure
    if backend.name == "torch":
        import diffquat.torch as tdq

        torch.manual_seed(0)
        head = tnn.RotationHead(5, "fisher", dtype=torch.float64)
        features, rotations = torch.tensor(x), torch.tensor(target)
        raw = head.linear(features)
        torch.testing.assert_close(head.fisher(features), raw.reshape(64, 3, 3))
        torch.testing.assert_close(head(features), tdq.matrix_fisher_mode(head.fisher(features)))
        with pytest.raises(ValueError, match=r"RotationHead.fisher: the head's representation is '6d'"):
            tnn.RotationHead(5, "6d").fisher(torch.zeros(5))
        optimizer = torch.optim.Adam(head.parameters(), lr=0.1)

        def nll() -> Any:
            return tdq.matrix_fisher_nll(head.fisher(features), rotations).mean()

        def losses() -> list[float]:
            with torch.no_grad():
                mode = tdq.matrix_fisher_mode(head.fisher(features))
                return [float(nll()), float(tdq.matrix_geodesic_distance(mode, rotations).mean())]

        first = losses()
        for _ in range(60):
            optimizer.zero_grad()
            nll().backward()
            grads = [p.grad for p in head.parameters() if p.grad is not None]
            assert all(bool(torch.all(torch.isfinite(g))) for g in grads)
            optimizer.step()
        last = losses()
    else:
        params = jnn.init_rotation_head(jax.random.key(0), 5, "fisher")
        features, rotations = jnp.asarray(x), jnp.asarray(target)

        def both(params: Any) -> tuple[Any, Any]:
            f = jnn.representation_to_fisher(features @ params["w"] + params["b"][None])
            mode = dq.matrix_fisher_mode(f)
            error = dq.matrix_geodesic_distance(mode, rotations).mean()
            return dq.matrix_fisher_nll(f, rotations).mean(), error

        optimizer = optax.adam(0.1)

        @jax.jit
        def step(params: Any, state: Any) -> tuple[Any, Any, Any]:
            grads = jax.grad(lambda p: both(p)[0])(params)
            with jax.numpy_dtype_promotion("standard"):
                updates, state = optimizer.update(grads, state, params)
            return optax.apply_updates(params, updates), state, grads

        state = optimizer.init(params)
        first = [float(v) for v in both(params)]
        for _ in range(60):
            params, state, grads = step(params, state)
            assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grads))
        last = [float(v) for v in both(params)]
    assert last[0] < first[0] - 1.0  # the NLL falls (it starts near 0: F ~ 0 is nearly uniform)
    assert last[1] < 0.5 * first[1]  # and the mode approaches the targets


def _readme_autocast_step() -> str:
    """The documented autocast training step (docs/api/torch.md: the python block that follows its
    mention of autocast)."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "api" / "torch.md").read_text()
    start = text.index("```python", text.index("A training step under `torch.autocast`"))
    return text[start + len("```python") : text.index("```", start + 1)]


@pytest.mark.parametrize("representation", tnn.REPRESENTATIONS)
def test_readme_autocast_training_step_runs_with_every_head(representation: str) -> None:
    """The documented ``torch.autocast(bfloat16)`` step, as written there, for each head: the head
    returns the autocast dtype (bfloat16, computed in float32 inside), the loss of bfloat16 and float32
    matrices promotes to float32 (it raised TypeError before), and the step leaves every parameter
    finite, with finite gradients, and moved."""
    code = _readme_autocast_step()
    assert 'representation = "6d"' in code
    code = code.replace('representation = "6d"', f"representation = {representation!r}")
    torch.manual_seed(0)
    scope: dict[str, Any] = {}

    # Run the block up to the optimizer step, keep copies of the parameters, then step.
    head, tail = code.split("optimizer.step()")
    exec(head, scope)  # the documentation's own code
    params = [*scope["backbone"].parameters(), *scope["head"].parameters()]
    before = [p.detach().clone() for p in params]
    exec("optimizer.step()" + tail, scope)
    assert scope["predicted"].dtype == torch.bfloat16
    assert scope["loss"].dtype == torch.float32
    assert bool(torch.isfinite(scope["loss"]))
    for p in params:
        assert p.grad is not None and bool(torch.all(torch.isfinite(p.grad)))
        assert bool(torch.all(torch.isfinite(p)))
    assert any(not torch.equal(p.detach(), b) for p, b in zip(params, before, strict=True))
