"""Policy files, read and written (:mod:`hybridoc.workflows.policy_format`, whose notes
describe the format): :func:`load_mlp_policy` and :func:`save_mlp_policy`."""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from hybridoc.workflows.policy_format.network import (
    MAX_PARAMETERS,
    MLP,
    NORMS,
    SATURATIONS,
    PolicyError,
    float_array,
)

__all__ = ["FORMAT", "VERSION", "load_mlp_policy", "save_mlp_policy"]

FORMAT = "hybridoc-mlp-policy"
"""The ``format`` entry of a policy JSON file."""
VERSION = 1
_KEYS = {
    "format", "version", "weights", "sha256", "input", "horizon", "layers", "activation",
    "saturation",
}  # fmt: skip
_MAX_JSON_BYTES = 1 << 20
_NPZ_SLACK = 1 << 20  # bytes of zip and .npy headers allowed beyond a file's described data

# ---------------------------------------------------------------------------- files


def _json_path(path: str | Path) -> Path:
    p = Path(path)
    return p if p.suffix.lower() == ".json" else p.with_suffix(".json")


def load_mlp_policy(path: str | Path) -> MLP:
    """Read a policy JSON file and its weights; nothing in them is executed.

    Parameters
    ----------
    path
        ``policy.json`` (module notes).

    Returns
    -------
    MLP

    Raises
    ------
    PolicyError
        A missing or unreadable file, JSON that is not the format, weights that do not
        match the description or the recorded SHA-256, non-finite numbers.
    """
    path = Path(path)
    where = repr(str(path))
    if not path.is_file():
        raise PolicyError(f"policy file {where} does not exist")
    from hybridoc.outputs import read_json

    # bounded in size and nesting (a file nested 200 000 deep is one clear error)
    spec = read_json(path, where, max_bytes=_MAX_JSON_BYTES, error=PolicyError)
    if not isinstance(spec, dict) or spec.get("format") != FORMAT:
        raise PolicyError(f"{where} is not a policy file: its 'format' must be {FORMAT!r}")
    if spec.get("version") != VERSION:
        raise PolicyError(
            f"{where}: version {spec.get('version')!r} is not supported (this hybridoc reads "
            f"version {VERSION})"
        )
    unknown = sorted(set(spec) - _KEYS)
    if unknown:
        raise PolicyError(f"{where}: unknown entries {', '.join(map(repr, unknown))}")
    layers = spec.get("layers")
    if (
        not isinstance(layers, list)
        or len(layers) < 2
        or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 1 for n in layers)
    ):
        raise PolicyError(
            f"{where}: 'layers' must list at least two positive integer widths (input, ..., "
            f"output), got {layers!r}"
        )
    parameters = sum((layers[k] + 1) * layers[k + 1] for k in range(len(layers) - 1))
    if parameters > MAX_PARAMETERS:
        raise PolicyError(
            f"{where}: 'layers' {_shown(layers)} describes {parameters} parameters, more than "
            f"the {MAX_PARAMETERS} a policy file may hold: refused before its weights are read"
        )
    weights = _weights_file(path, spec, where)
    # what the file may hold: the layers, the normalisations, at most 16 bytes a number
    shapes = {f"layer{k}.{part}": shape for k in range(len(layers) - 1)
              for part, shape in (("weight", (layers[k + 1], layers[k])),
                                  ("bias", (layers[k + 1],)))}  # fmt: skip
    for name, side in NORMS.items():
        shapes[name] = (layers[-1],) if side == "nu" else None  # nx: checked by the MLP
    _check_weights_size(weights, parameters + 4 * max(layers), where)
    arrays = _read_npz(weights, spec.get("sha256"), where, shapes)
    Ws, bs = [], []
    for k in range(len(layers) - 1):
        W, b = arrays.pop(f"layer{k}.weight", None), arrays.pop(f"layer{k}.bias", None)
        if W is None or b is None:
            raise PolicyError(f"{weights.name!r} lacks layer{k}.weight or layer{k}.bias")
        if W.shape != (layers[k + 1], layers[k]) or b.shape != (layers[k + 1],):
            raise PolicyError(
                f"{weights.name!r}: layer {k} has weight {W.shape} and bias {b.shape}; "
                f"{where} describes ({layers[k + 1]}, {layers[k]}) and ({layers[k + 1]},)"
            )
        Ws.append(W)
        bs.append(b)
    norms = {k: arrays.pop(k) for k in list(arrays) if k in NORMS}
    if arrays:
        raise PolicyError(
            f"{weights.name!r} holds arrays {', '.join(map(repr, sorted(arrays)))} that "
            f"{where} does not describe"
        )
    horizon = spec.get("horizon")
    if horizon is not None and (isinstance(horizon, bool) or not isinstance(horizon, int | float)):
        raise PolicyError(f"{where}: 'horizon' must be a number or null, got {horizon!r}")
    lower, upper = _saturation(spec.get("saturation"), layers[-1], where)
    try:
        return MLP(
            tuple(Ws), tuple(bs),
            activation=spec.get("activation", "tanh"), input=spec.get("input", "t,state"),
            horizon=horizon, output_min=lower, output_max=upper, **norms,
        )  # fmt: skip
    except PolicyError as exc:
        raise PolicyError(f"{where}: {exc}") from None


def _saturation(entry: Any, nu: int, where: str) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The bounds of a ``saturation`` entry (module notes); absent or ``null``: none."""
    if entry is None:
        return None, None
    form = "{'kind': 'clip', 'lower': [...], 'upper': [...]}"
    if not isinstance(entry, dict) or set(entry) != {"kind", "lower", "upper"}:
        raise PolicyError(f"{where}: 'saturation' must be {form} or null, got {entry!r}")
    if entry["kind"] not in SATURATIONS:
        raise PolicyError(
            f"{where}: saturation kind {entry['kind']!r} is not one of {', '.join(SATURATIONS)}"
        )
    sides = []
    for name, missing in (("lower", -np.inf), ("upper", np.inf)):
        values = entry[name]
        if not isinstance(values, list) or len(values) != nu:
            raise PolicyError(
                f"{where}: saturation {name!r} must list {nu} bounds (one per control, null "
                f"for none), got {values!r}"
            )
        for v in values:
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float)):
                raise PolicyError(f"{where}: saturation {name!r} holds {v!r}, not a number")
        sides.append(np.array([missing if v is None else float(v) for v in values]))
    return sides[0], sides[1]


def _weights_file(path: Path, spec: dict[str, Any], where: str) -> Path:
    name = spec.get("weights")
    if not isinstance(name, str) or not name:
        raise PolicyError(f"{where}: 'weights' must name the .npz file beside it")
    # a bare name in the same folder: a description cannot point at other files
    if Path(name).name != name or name in (".", ".."):
        raise PolicyError(f"{where}: 'weights' must be a file name in its folder, got {name!r}")
    weights = path.parent / name
    if not weights.is_file():
        raise PolicyError(f"{where} names the weights file {name!r}, which does not exist")
    return weights


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _check_weights_size(weights: Path, numbers: int, where: str) -> None:
    """Refuse a weights file larger than the numbers its description holds can take (16
    bytes each, plus headers) before reading it."""
    try:
        size = weights.stat().st_size
    except OSError as exc:
        raise PolicyError(f"cannot read {str(weights)!r}: {exc.strerror or exc}") from None
    if size > 16 * numbers + _NPZ_SLACK:
        raise PolicyError(
            f"{str(weights)!r} holds {size} bytes, more than the {numbers} numbers that "
            f"{where} describes can take: refused before it is read"
        )


def _declared_shapes(data: bytes, weights: Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """The shapes and types the members of an ``.npz`` file declare in their headers (read
    without the arrays: a header may declare far more than the file holds)."""
    import zipfile

    from numpy.lib import format as npformat

    out: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for info in zf.infolist():
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            with zf.open(info) as fh:
                head = io.BytesIO(fh.read(65536 + 16))
            version = npformat.read_magic(head)
            read = (
                npformat.read_array_header_1_0
                if version == (1, 0)
                else npformat.read_array_header_2_0
            )
            shape, _, dtype = read(head)
            out[name] = (tuple(int(n) for n in shape), np.dtype(dtype))
    return out


def _check_declared(
    data: bytes, weights: Path, where: str, shapes: dict[str, tuple[int, ...] | None]
) -> None:
    """The members of a weights file, by the shapes their headers declare, against its
    description (``shapes``: name -> shape, ``None`` for a state-sized vector), with the
    messages of the checks after the load; nothing is allocated for a member."""
    try:
        members = _declared_shapes(data, weights)
    except Exception as exc:  # zipfile and numpy's header parser raise many kinds
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise PolicyError(f"cannot read {str(weights)!r} as .npz weights: {first}") from None
    for name, (_, dtype) in members.items():
        if dtype.hasobject:  # a pickle: never read
            raise PolicyError(
                f"cannot read {str(weights)!r} as .npz weights: {name} is an object array"
            )
        if dtype.kind not in "fiu":
            raise PolicyError(f"{weights.name!r}: {name} must hold real numbers, got dtype {dtype}")
    declared = {name: shape for name, (shape, _) in members.items()}
    unknown = sorted(set(declared) - set(shapes))
    if unknown:
        raise PolicyError(
            f"{weights.name!r} holds arrays {', '.join(map(repr, unknown))} that {where} does "
            "not describe"
        )
    k = 0
    while f"layer{k}.weight" in shapes:
        W, b = (declared.get(f"layer{k}.{part}") for part in ("weight", "bias"))
        want_W, want_b = shapes[f"layer{k}.weight"], shapes[f"layer{k}.bias"]
        if W is not None and b is not None and (W != want_W or b != want_b):
            raise PolicyError(
                f"{weights.name!r}: layer {k} has weight {W} and bias {b}; {where} describes "
                f"{want_W} and {want_b}"
            )
        k += 1
    for name in NORMS:
        shape = declared.get(name)
        if shape is None:
            continue
        want = shapes[name]
        if (want is None and (len(shape) != 1 or shape[0] > _NPZ_SLACK)) or (
            want is not None and shape != want
        ):
            n = "the state's" if want is None else str(want[0])
            raise PolicyError(f"{weights.name!r}: {name} must have {n} entries, got shape {shape}")


def _read_npz(
    weights: Path,
    sha: Any,
    where: str,
    shapes: dict[str, tuple[int, ...] | None] | None = None,
) -> dict[str, np.ndarray]:
    """The arrays of a weights file; with ``shapes`` (name -> the shape its description
    gives, ``None``: any vector), each member's declared shape is checked against it before
    any array is read, so that a header declaring a huge array allocates nothing."""
    try:
        data = weights.read_bytes()
    except OSError as exc:
        raise PolicyError(f"cannot read {str(weights)!r}: {exc.strerror or exc}") from None
    if sha is not None:
        if not isinstance(sha, str) or hashlib.sha256(data).hexdigest() != sha.lower():
            raise PolicyError(
                f"{str(weights)!r} does not match the SHA-256 recorded in {where}: the weights "
                "were changed or belong to another policy"
            )
    if shapes is not None:
        _check_declared(data, weights, where, shapes)
    try:
        # allow_pickle=False: an object array in the file is refused, never unpickled
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            return {k: float_array(npz[k], f"{weights.name!r}: {k}") for k in npz.files}
    except PolicyError:
        raise
    except Exception as exc:  # numpy raises ValueError, OSError, zipfile errors, ...
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise PolicyError(f"cannot read {str(weights)!r} as .npz weights: {first}") from None


def save_mlp_policy(
    policy: Any,
    path: str | Path,
    *,
    input: str | None = None,
    horizon: float | None = None,
    state_mean: Any = None,
    state_scale: Any = None,
    output_offset: Any = None,
    output_scale: Any = None,
    output_min: Any = None,
    output_max: Any = None,
) -> Path:
    """Write a policy as ``<stem>.json`` and ``<stem>.npz`` (module notes).

    Parameters
    ----------
    policy
        An :class:`MLP`; a :class:`hybridoc.workflows.training.MLPPolicy` (its
        normalisations and horizon come with it); or a ``torch.nn.Sequential`` of
        ``Linear`` layers with one kind of activation (``Tanh``, ``ReLU``, ``Sigmoid``)
        between them, described by the keywords.
    path
        ``<stem>.json`` (or a stem): the JSON file; the weights go beside it.
    input, horizon, state_mean, state_scale, output_offset, output_scale, output_min, output_max
        For a ``Sequential`` only: what it reads (``"t,state"`` or ``"state"``, default
        ``"state"``), the normalisations of :class:`MLP` and the bounds its output is
        clipped to (the JSON's ``saturation``).

    Returns
    -------
    Path
        The JSON file.

    Raises
    ------
    PolicyError
        A module that is not such an MLP (another layer kind, mixed activations).
    hybridoc.errors.HybridocError
        A link, or a file hybridoc did not write, at either name (:mod:`hybridoc.outputs`);
        a file that cannot be written.
    """
    extra = {
        "input": input, "horizon": horizon, "state_mean": state_mean,
        "state_scale": state_scale, "output_offset": output_offset,
        "output_scale": output_scale, "output_min": output_min, "output_max": output_max,
    }  # fmt: skip
    mlp = _as_mlp(policy, extra)
    json_path = _json_path(path)
    npz_path = json_path.with_suffix(".npz")
    arrays: dict[str, np.ndarray] = {}
    for k, (W, b) in enumerate(zip(mlp.weights, mlp.biases, strict=True)):
        arrays[f"layer{k}.weight"] = W
        arrays[f"layer{k}.bias"] = b
    for name in NORMS:
        arrays[name] = getattr(mlp, name)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    data = buf.getvalue()
    spec = {
        "format": FORMAT,
        "version": VERSION,
        "weights": npz_path.name,
        "sha256": hashlib.sha256(data).hexdigest(),
        **mlp.description(),
    }
    from hybridoc.outputs import check_targets, write_bytes, write_text

    # by the rules of hybridoc.outputs (atomically, never through a link or over a user's
    # file), both names checked before either is written
    check_targets(npz_path, json_path)
    write_bytes(npz_path, data)
    write_text(json_path, json.dumps(spec, indent=2) + "\n")
    return json_path


def _as_mlp(policy: Any, extra: dict[str, Any]) -> MLP:
    """An :class:`MLP` from what :func:`save_mlp_policy` accepts."""
    given = {k: v for k, v in extra.items() if v is not None}
    if isinstance(policy, MLP):
        if given:
            raise PolicyError(f"an MLP carries its own settings; got {', '.join(given)}")
        return policy
    net = getattr(policy, "net", None)
    if net is not None and hasattr(policy, "s_mean") and hasattr(policy, "u_offset"):
        # training.MLPPolicy: the form this format was made for
        if given:
            raise PolicyError(f"an MLPPolicy carries its own settings; got {', '.join(given)}")
        Ws, bs, act = _sequential_layers(net)

        def arr(x: Any) -> np.ndarray:
            return x.detach().cpu().numpy().astype(float)

        u_min, u_max = getattr(policy, "u_min", None), getattr(policy, "u_max", None)
        return MLP(
            Ws, bs, activation=act, input="t,state", horizon=float(policy.horizon),
            state_mean=arr(policy.s_mean), state_scale=arr(policy.s_scale),
            output_offset=arr(policy.u_offset), output_scale=arr(policy.u_scale),
            output_min=None if u_min is None else arr(u_min),
            output_max=None if u_max is None else arr(u_max),
        )  # fmt: skip
    if type(policy).__name__ == "Sequential":
        Ws, bs, act = _sequential_layers(policy)
        return MLP(Ws, bs, activation=act, **{"input": "state", **given})
    raise PolicyError(
        "save_mlp_policy takes an MLP, a training.MLPPolicy or a torch.nn.Sequential of Linear "
        f"layers and activations, got {type(policy).__name__}"
    )


_TORCH_ACTIVATIONS = {"Tanh": "tanh", "ReLU": "relu", "Sigmoid": "sigmoid"}


def _sequential_layers(net: Any) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...], str]:
    """Weights, biases and the activation of a ``Sequential`` of ``Linear`` and activations."""
    Ws: list[np.ndarray] = []
    bs: list[np.ndarray] = []
    acts: list[str] = []
    expect_linear = True
    for m in net:
        kind = type(m).__name__
        if kind == "Identity" or kind == "Dropout":
            continue  # no-ops in evaluation
        if kind == "Linear":
            if not expect_linear:
                raise PolicyError("two Linear layers in a row without an activation between them")
            Ws.append(m.weight.detach().cpu().numpy().astype(float))
            b = m.bias
            bs.append(
                np.zeros(m.out_features) if b is None else b.detach().cpu().numpy().astype(float)
            )
            expect_linear = False
        elif kind in _TORCH_ACTIVATIONS:
            if expect_linear:
                raise PolicyError(f"{kind} must follow a Linear layer")
            acts.append(_TORCH_ACTIVATIONS[kind])
            expect_linear = True
        else:
            raise PolicyError(
                f"layer {kind} has no form in the policy format (Linear, "
                f"{', '.join(_TORCH_ACTIVATIONS)})"
            )
    if not Ws:
        raise PolicyError("the network has no Linear layer")
    if expect_linear:
        raise PolicyError("the network ends with an activation; the format's last layer is Linear")
    if len(set(acts)) > 1:
        raise PolicyError(f"the format has one activation for all layers, got {sorted(set(acts))}")
    return tuple(Ws), tuple(bs), acts[0] if acts else "identity"
