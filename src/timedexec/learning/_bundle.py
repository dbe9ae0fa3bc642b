"""Model bundles: trained delay models as numeric arrays plus a JSON manifest; a fast predictor.

A bundle is a directory with two files (DESIGN.md, "Model bundle"):

``arrays.npz``
    Numeric arrays only, loaded with ``allow_pickle=False``. Written deterministically
    (sorted members, fixed time stamps): the same training gives the same bytes.
``manifest.json``
    Robot, controller period, feature order, units, training-data hashes, CV scores and
    noise floor, model summaries, package version and the sha256 of ``arrays.npz``.

Loading checks the arrays' hash and, when asked, the robot and controller period; a
mismatch raises :class:`~timedexec.errors.ModelError`. Nothing at load or predict time
needs scikit-learn or pickle: Gaussian processes are stored as their sufficient statistics
(condition inputs, means, counts) and hyperparameters and re-conditioned at load with the
same code that trained them (:func:`~timedexec.learning._gpcore.build_predictor`).
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import warnings
import zipfile
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from timedexec._files import make_dir, write_atomic
from timedexec._types import FloatArray
from timedexec._version import __version__
from timedexec.errors import ConfigError, ModelError, ThermalStateWarning
from timedexec.learning._calibrate import (
    BOUND_CONFIDENCE,
    BOUND_RULE,
    CALIBRATED_METHOD,
    DELAYS,
    GAUSSIAN_Z95,
    STD_SCALE_RULE,
    DelayBounds,
    read_per_model,
)
from timedexec.learning._features import encode_inputs, feature_names
from timedexec.learning._gpcore import GPPredictor
from timedexec.learning._method import DelayMethod, ModelInputs, Predictor
from timedexec.learning._registry import METHODS, get_method
from timedexec.learning._shipped import BUNDLED_MODELS, bundled_model_dir
from timedexec.learning._thermal import thermal_mismatch
from timedexec.learning._threads import BLAS_PIN, BlasPin

__all__ = ["ARRAYS_NAME", "BUNDLE_FORMAT", "MANIFEST_NAME", "DelayModel", "DelayPrediction"]


BUNDLE_FORMAT = "timedexec-delay-model"
BUNDLE_VERSION = 1
MANIFEST_NAME = "manifest.json"
ARRAYS_NAME = "arrays.npz"
_DELAYS = DELAYS


class DelayPrediction(NamedTuple):
    """Predicted delays for one command (floats) or many (arrays of shape (n,)), s.

    A named tuple: fields by name, or unpacked in this order.

    Attributes
    ----------
    actuation_mean, response_mean : float or ndarray
        Expected delay, s.
    actuation_std, response_std : float or ndarray
        Standard deviation of the delay of a single future trial, s: for the GP
        ``c · sqrt(latent variance + trial noise variance)`` with the bundle's calibration
        factor ``c >= 1`` (``std_scale`` in the manifest, from the cross-validation; 1 for
        bundles without it); for the other methods their cross-validated RMS error (their
        training RMS error without CV). This is what timing bounds are built from.
    actuation_latent_std, response_latent_std : float or ndarray
        GP only: standard deviation of the *mean* delay at this input (model uncertainty
        without the trial-to-trial scatter), s: ``sqrt(std² - σ_n²)``. The trial noise
        ``σ_n`` is measured by the replicates, so the calibration's extra variance is
        model error, i.e. uncertainty of the mean: ``std² = latent_std² + σ_n²`` holds
        before and after calibration. NaN for the other methods.
    """

    actuation_mean: Any
    actuation_std: Any
    response_mean: Any
    response_std: Any
    actuation_latent_std: Any
    response_latent_std: Any

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict (arrays become lists)."""
        return {
            k: (v.tolist() if isinstance(v, np.ndarray) else float(v))
            for k, v in self._asdict().items()
        }


# ------------------------------------------------------------------ files


def _npz_bytes(arrays: Mapping[str, NDArray[Any]]) -> bytes:
    """A deterministic .npz: sorted members, fixed time stamps, deflate."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            arr = np.asarray(arrays[name])
            if not arr.flags.c_contiguous:  # (ascontiguousarray would turn 0-d into 1-d)
                arr = arr.copy(order="C")
            if arr.dtype == object:
                raise ModelError(f"bundle array {name!r} has dtype object; only numbers are stored")
            member = io.BytesIO()
            np.lib.format.write_array(member, arr, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def _inside_bundle(manifest_path: Path, name: Any) -> Path:
    """The bundle file ``name`` (from the manifest), which must resolve inside the bundle
    folder: a manifest cannot make timedexec read a file elsewhere.

    Raises
    ------
    ModelError
        A name that is not a plain string, or that resolves (``..``, an absolute path, a
        symlink) outside the bundle folder.
    """
    folder = manifest_path.parent
    if not isinstance(name, str) or not name:
        raise ModelError(f"{manifest_path}: arrays.file must be a file name, got {name!r}")
    path = folder / name
    root = folder.resolve()
    resolved = path.resolve()
    if resolved.parent != root and root not in resolved.parents:
        raise ModelError(
            f"{manifest_path}: arrays.file {name!r} points outside the bundle folder {folder} "
            f"(to {resolved}); a bundle reads only its own files: restore the manifest or "
            "retrain"
        )
    return path


def _check_arrays(model: DelayModel, arrays_path: Path) -> None:
    """Refuse a bundle whose arrays do not fit together (truncated or tampered arrays that
    kept a matching hash), before any prediction could fail or mislead: each model's arrays
    against what its method declares (:meth:`DelayMethod.check_arrays`).

    Raises
    ------
    ModelError
        Naming the model (method, delay, model key), the array and what is wrong; or a
        method this timedexec does not know.
    """
    for name in model.methods:
        if name not in METHODS:
            raise ModelError(
                f"{arrays_path}: unknown method {name!r} in the manifest; this timedexec "
                f"knows {', '.join(METHODS)}"
            )
        method = get_method(name)
        for delay in _DELAYS:
            for key in model.keys:
                problem = method.check_arrays(model._group(name, delay, key), model._inputs(key))
                if problem:
                    raise ModelError(
                        f"{arrays_path}: the {name} model of the {delay} ({key}) is corrupt: "
                        f"{problem}; the arrays are truncated or were altered — retrain or "
                        "restore the bundle"
                    )


def _robot_of(robot: Any) -> tuple[str | None, float | None]:
    if robot is None:
        return None, None
    if isinstance(robot, str):
        return robot, None
    name = getattr(robot, "name", None)
    period = getattr(robot, "controller_period_s", None)
    if not isinstance(name, str):
        raise ConfigError(f"robot must be a name or a RobotSpec, got {robot!r}")
    return name, float(period) if period is not None else None


def _default_method(methods: Sequence[str], cv: Mapping[str, Any] | None) -> str:
    """The method a bundle answers with when none is named: the GP where it has one (its
    variance is what timing bounds are made of), else the method with the least CV error
    of the actuation delay (averaged over the columns), else the first it holds."""
    if CALIBRATED_METHOD in methods:
        return CALIBRATED_METHOD
    if cv is not None:
        scores = cv.get("actuation_delay", {})

        def error(method: str) -> float:
            value = scores.get(method, {}).get("average", math.inf)
            return float(value) if math.isfinite(float(value)) else math.inf

        best = min(methods, key=error)
        if math.isfinite(error(best)):
            return best
    return methods[0]


# ------------------------------------------------------------------ model


class DelayModel:
    """Trained delay models of one robot at one controller period, fast to query.

    Build one with :func:`~timedexec.learning.train_delay_models` (or ``timedexec
    train``), or :meth:`load` a bundle. :meth:`predict` answers one command in a few tens
    of µs with the per-joint Gaussian processes by default.

    Examples
    --------
    >>> model = DelayModel.load("my-ur10-model", robot="ur10")  # doctest: +SKIP
    >>> p = model.predict(joint=2, direction=1, q=[0, -1.57, 1.2, -1.2, -1.57, 0])  # doctest: +SKIP
    >>> p.actuation_mean, p.actuation_std  # s  # doctest: +SKIP
    """

    def __init__(
        self,
        manifest: Mapping[str, Any],
        arrays: Mapping[str, NDArray[Any]],
        *,
        path: Path | None = None,
    ) -> None:
        self.manifest: dict[str, Any] = dict(manifest)
        self._arrays = dict(arrays)
        self.path = path
        self.robot: str = str(manifest["robot"])
        self.period_s: float = float(manifest["controller_period_s"])
        self.joints: tuple[int, ...] = tuple(int(j) for j in manifest["joints"])
        self.methods: tuple[str, ...] = tuple(manifest["methods"])
        self.keys: tuple[str, ...] = tuple(manifest["models"])
        self.time_input: bool = bool(manifest.get("time_input", False))
        default = manifest.get("time_default_s")
        self.time_default_s: float | None = None if default is None else float(default)
        thermal = manifest.get("thermal_state")
        #: The thermal states the training saw (``clock``, ``range_s``, ``state``), or None
        #: (bundles from before it was recorded); see :mod:`timedexec.learning._thermal`.
        self.thermal_state: dict[str, Any] | None = (
            dict(thermal) if isinstance(thermal, dict) else None
        )
        self._thermal_warned = False
        self._predictors: dict[tuple[str, str, str], Any] = {}  # (method, delay, key)
        self._mean_std: dict[tuple[str, str, str], float] = {}
        # (method, joint, combined) -> (act, resp, fused pair or None, c_act², c_resp²)
        self._fast: dict[tuple[str, int, bool], tuple[Any, Any, Any, float, float]] = {}
        self.std_scale: dict[str, dict[str, float]] = read_per_model(
            manifest.get("std_scale"), self.keys, "std_scale"
        )
        # half-widths of the GP's 95 % bounds in calibrated stds (``bound_z[delay][key]``
        # in the manifest, see bound_z()); empty for older bundles
        self._bound_z_table: dict[str, dict[str, float]] = read_per_model(
            manifest.get("bound_z"), self.keys, "bound_z"
        )
        self.default_method: str = _default_method(self.methods, self.cv_scores_ms)

    # ---------------------------------------------------------- building
    @classmethod
    def from_training(
        cls,
        finals: Mapping[tuple[str, str, str], Mapping[str, Any]],
        *,
        robot: str,
        period_s: float,
        joints: Sequence[int],
        keys: Sequence[str],
        methods: Sequence[str],
        cv: Any,
        training: Mapping[str, Any],
        time_input: bool = False,
        time_range_s: tuple[float, float] = (0.0, 0.0),
        thermal: Mapping[str, Any] | None = None,
    ) -> DelayModel:
        """Assemble a model from final fits ``{(method, delay, key): {"arrays", "train_rmse_s", "info"}}``.

        The GP's std calibration (``cv.std_scale``, ``cv.std_held_out``) goes into the
        manifest as ``std_scale`` and ``std_calibration``; without CV (or without "gpr")
        neither is written and the GP's std is used as it is (factor 1). ``thermal``
        (:func:`~timedexec.learning._thermal.thermal_state`) becomes ``thermal_state``.
        """
        arrays: dict[str, NDArray[Any]] = {}
        models: dict[str, Any] = {}
        for (method, delay, key), out in sorted(finals.items()):
            for name, arr in out["arrays"].items():
                arrays[f"{method}.{delay}.{key}.{name}"] = np.asarray(arr)
            entry = models.setdefault(method, {}).setdefault(delay, {})
            entry[key] = {"train_rmse_ms": 1e3 * float(out["train_rmse_s"]), **out["info"]}
        manifest: dict[str, Any] = {
            "format": BUNDLE_FORMAT,
            "format_version": BUNDLE_VERSION,
            "robot": robot,
            "controller_period_s": float(period_s),
            "joints": [int(j) for j in joints],
            "models": list(keys),
            "methods": list(methods),
            "delays": list(_DELAYS),
            "units": {
                "q": "rad",
                "direction": "+1 or -1",
                "delays": "s",
                "cv_scores": "ms",
                "train_rmse": "ms",
            },
            "inputs": (
                "start configuration q1..q6 as sin/cos pairs, direction (+1/-1); the combined "
                "model adds one-hot joint columns"
                + ("; last, the sweep time t_h in hours" if time_input else "")
            ),
            "feature_order": {
                "per_joint": list(feature_names(None, time_input)),
                "combined": list(feature_names(tuple(int(j) for j in joints), time_input)),
            },
            "time_input": bool(time_input),
            # predictions default to the end of the calibration sweep: the warm robot
            "time_default_s": float(time_range_s[1]) if time_input else None,
            "time_range_s": [float(time_range_s[0]), float(time_range_s[1])],
            "thermal_state": None if thermal is None else dict(thermal),
            "training_data": dict(training),
            "cv": None
            if cv is None
            else {
                "folds": cv.folds,
                "grouping": "start configuration",
                "scores_ms": cv.to_dict(),
                "noise_floor_ms": cv.noise_floor_ms,
            },
            "model_info": models,
            "package_version": __version__,
        }
        scale = getattr(cv, "std_scale", None) if cv is not None else None
        if scale and CALIBRATED_METHOD in methods:
            manifest["std_scale"] = {
                d: {k: float(v) for k, v in by_key.items()} for d, by_key in scale.items()
            }
            manifest["std_calibration"] = {
                "method": CALIBRATED_METHOD,
                "applies_to": "actuation_std, response_std (latent std: sqrt(std^2 - noise^2))",
                "rule": STD_SCALE_RULE,
                "folds": cv.folds,
                "held_out": getattr(cv, "std_held_out", {}),
            }
            bound_z = getattr(cv, "bound_z", None)
            if bound_z:
                manifest["bound_z"] = {
                    d: {k: float(v) for k, v in by_key.items()} for d, by_key in bound_z.items()
                }
                manifest["std_calibration"]["bounds"] = {
                    "confidence": BOUND_CONFIDENCE,
                    "rule": BOUND_RULE,
                }
        return cls(manifest, arrays)

    # -------------------------------------------------------------- files
    def save(self, directory: str | os.PathLike[str]) -> Path:
        """Write ``arrays.npz`` and ``manifest.json`` into ``directory`` (created); return it."""
        out = make_dir(directory, "bundle directory")
        data = _npz_bytes(self._arrays)
        manifest = dict(self.manifest)
        manifest["arrays"] = {
            "file": ARRAYS_NAME,
            "sha256": hashlib.sha256(data).hexdigest(),
            "bytes": len(data),
        }
        write_atomic(out / ARRAYS_NAME, data)
        write_atomic(out / MANIFEST_NAME, json.dumps(manifest, indent=2) + "\n")
        self.manifest = manifest
        self.path = out
        return out

    @classmethod
    def load(
        cls,
        path: str | os.PathLike[str],
        *,
        robot: Any = None,
        period_s: float | None = None,
    ) -> DelayModel:
        """Load a bundle (its directory or its manifest) and check it.

        Parameters
        ----------
        path : path or str
            Bundle directory, or its ``manifest.json``, or the name of a shipped model
            (:data:`~timedexec.learning.BUNDLED_MODELS`; see ``models/README.md``).
        robot : str or RobotSpec, optional
            Refuse a bundle trained for another robot. A RobotSpec also fixes the period.
        period_s : float, optional
            Refuse a bundle trained at another controller period, s.

        Raises
        ------
        ModelError
            Missing or unreadable files, an unknown format, arrays whose sha256 differs from
            the manifest's, or a bundle for another robot or period.
        """
        p = Path(path)
        if not p.exists() and str(path) in BUNDLED_MODELS:
            p = bundled_model_dir(str(path))  # a shipped model, by name
        manifest_path = p / MANIFEST_NAME if p.is_dir() else p
        try:
            manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ModelError(
                f"no model bundle at {p}: {manifest_path} does not exist (train one with "
                "`timedexec train DELAYS.csv --out DIR`)"
            ) from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ModelError(f"cannot read the bundle manifest {manifest_path}: {exc}") from exc
        if not isinstance(manifest, dict) or manifest.get("format") != BUNDLE_FORMAT:
            raise ModelError(f"{manifest_path} is not a timedexec delay-model manifest")
        version = manifest.get("format_version")
        if not isinstance(version, int) or version > BUNDLE_VERSION:
            raise ModelError(
                f"{manifest_path}: bundle format version {version!r} is newer than this "
                f"timedexec supports ({BUNDLE_VERSION}); upgrade timedexec"
            )
        info = manifest.get("arrays") or {}
        if not isinstance(info, dict):
            raise ModelError(f"{manifest_path}: 'arrays' must be an object, got {info!r}")
        arrays_path = _inside_bundle(manifest_path, info.get("file", ARRAYS_NAME))
        try:
            data = arrays_path.read_bytes()
        except OSError as exc:
            raise ModelError(
                f"cannot read the bundle arrays {arrays_path}: {exc.strerror or exc}"
            ) from exc
        digest = hashlib.sha256(data).hexdigest()
        if digest != info.get("sha256"):
            raise ModelError(
                f"{arrays_path}: sha256 {digest} does not match the manifest's "
                f"{info.get('sha256')}; the arrays are corrupt or were replaced — retrain or "
                "restore the bundle"
            )
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise ModelError(f"cannot read the bundle arrays {arrays_path}: {exc}") from exc
        except AttributeError:  # a bare .npy, not an archive of named arrays
            raise ModelError(
                f"cannot read the bundle arrays {arrays_path}: not an .npz archive"
            ) from None
        try:
            model = cls(manifest, arrays, path=manifest_path.parent)
        except ModelError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelError(f"{manifest_path}: incomplete manifest ({exc})") from exc
        _check_arrays(model, arrays_path)
        model.check(robot, period_s)
        return model

    def check(self, robot: Any = None, period_s: float | None = None) -> None:
        """Raise ModelError unless the bundle is for ``robot`` (name or RobotSpec) at ``period_s``."""
        name, spec_period = _robot_of(robot)
        period = period_s if period_s is not None else spec_period
        where = f"model bundle {self.path}" if self.path else "the delay model"
        mine = f"{self.robot!r} at a controller period of {self.period_s * 1e3:g} ms"
        if name is not None and name != self.robot:
            raise ModelError(
                f"{where} is for robot {mine}; refusing it for robot {name!r}: train a model "
                f"on {name}'s delay table (timedexec train)"
            )
        if period is not None and not math.isclose(float(period), self.period_s, rel_tol=1e-9):
            raise ModelError(
                f"{where} is for robot {mine}; refusing it at {float(period) * 1e3:g} ms: the "
                "delays depend on the controller period; train a model at this period"
            )

    # ------------------------------------------------------------ queries
    @property
    def cv_scores_ms(self) -> dict[str, Any] | None:
        """CV scores ``{delay: {method: {column: ms}}}`` of the training run, or None."""
        cv = self.manifest.get("cv")
        return None if cv is None else cv["scores_ms"]  # type: ignore[no-any-return]

    @property
    def noise_floor_ms(self) -> dict[str, Any] | None:
        """Replicate scatter ``{delay: {column: ms}}``, or None."""
        cv = self.manifest.get("cv")
        return None if cv is None else cv["noise_floor_ms"]  # type: ignore[no-any-return]

    def _key(self, joint: int, combined: bool) -> str:
        if combined:
            if "combined" not in self.keys:
                raise ModelError(
                    f"this bundle has no combined model (models: {', '.join(self.keys)})"
                )
            if joint not in self.joints:
                raise ModelError(
                    f"joint {joint!r} is unknown to this bundle; it models joints "
                    f"{', '.join(map(str, self.joints))}"
                )
            return "combined"
        if str(joint) not in self.keys:
            raise ModelError(
                f"joint {joint!r} is unknown to this bundle; it models joints "
                f"{', '.join(map(str, self.joints))} (calibrate and train that joint)"
            )
        return str(joint)

    def _group(self, method: str, delay: str, key: str) -> dict[str, NDArray[Any]]:
        prefix = f"{method}.{delay}.{key}."
        out = {k[len(prefix) :]: v for k, v in self._arrays.items() if k.startswith(prefix)}
        if not out:
            raise ModelError(f"the bundle holds no {method} model of {delay} for model {key!r}")
        return out

    def _inputs(self, key: str) -> ModelInputs:
        return ModelInputs.of(self.robot, key, self.joints, self.time_input)

    def _predictor(self, method: str, delay: str, key: str) -> Predictor:
        """The deployed predictor of one model, built from its arrays on first use."""
        pred = self._predictors.get((method, delay, key))
        if pred is None:
            group = self._group(method, delay, key)
            pred = get_method(method).predictor(group, self._inputs(key))
            self._predictors[(method, delay, key)] = pred
        return pred

    def _trial_std(self, method: str, delay: str, key: str) -> float:
        """A method without a variance: its CV RMS error (else its training RMS error), s."""
        std_s = self._mean_std.get((method, delay, key))
        if std_s is None:
            cv = self.cv_scores_ms
            if cv is not None and not math.isnan(cv[delay][method][key]):
                std_s = cv[delay][method][key] * 1e-3
            else:
                std_s = self.manifest["model_info"][method][delay][key]["train_rmse_ms"] * 1e-3
            self._mean_std[(method, delay, key)] = std_s
        return std_s

    def _method(self, method: str) -> DelayMethod:
        if method not in self.methods:
            raise ModelError(
                f"method {method!r} is not in this bundle; it holds {', '.join(self.methods)}"
            )
        return get_method(method)

    def predict(
        self,
        *,
        joint: int,
        direction: int,
        q: ArrayLike,
        t_s: float | None = None,
        method: str | None = None,
        combined: bool = False,
    ) -> DelayPrediction:
        """Delays of one single-joint command: means and standard deviations, s.

        Parameters
        ----------
        joint : int
            Actuated joint (1-based); must be one the bundle models.
        direction : int
            +1 or -1.
        q : array, shape (6,)
            Start configuration, rad.
        t_s : float, optional
            Time since the robot's power-on, s (bundles whose ``thermal_state`` has the
            power-on clock; older bundles: on the calibration sweep's clock). The time input
            of bundles with one (``time_input``; default the end of the sweep, warm); for
            every bundle that knows its thermal states, checked against them: a query about
            another (a warm robot's model asked about a cold robot, or the reverse; see
            :mod:`timedexec.learning._thermal`) warns once per model
            (:class:`~timedexec.errors.ThermalStateWarning`). Refused by bundles with
            neither.
        method : str, optional
            One of the bundle's methods (``methods``): "gpr", "nn", "rt", "median", ...
            (:data:`~timedexec.learning.METHODS`); default :attr:`default_method` (the GP
            where the bundle has one).
        combined : bool
            Use the combined model instead of the joint's own.

        Returns
        -------
        DelayPrediction
            Floats in s.
        """
        if method is None:
            method = self.default_method
        fast = self._fast.get((method, joint, combined))
        if fast is None and (spec := self._method(method)).variance:
            # a method with a variance: its predictors (fused where it can), cached
            key = self._key(joint, combined)
            act = self._predictor(method, "actuation_delay", key)
            resp = self._predictor(method, "response_delay", key)
            pair = spec.pair(act, resp) if spec.pair is not None else None
            ca = self._scale(method, "actuation_delay", key)
            cr = self._scale(method, "response_delay", key)
            fast = (act, resp, pair, ca * ca, cr * cr)
            self._fast[(method, joint, combined)] = fast
        if fast is not None:
            x = self._encode_one(joint, direction, q, combined, t_s)
            act, resp, pair, ca2, cr2 = fast
            BLAS_PIN.enter()
            try:
                if pair is not None:
                    am, av, rm, rv = pair.predict_one(x)
                else:
                    am, av = act.predict_one(x)
                    rm, rv = resp.predict_one(x)
            finally:
                BLAS_PIN.exit()
            an, rn = act.noise_var_s2, resp.noise_var_s2
            # calibrated: std² = c²(var + σ_n²), latent² = std² - σ_n² = c²var + (c²-1)σ_n²
            # (with c = 1 exactly the uncalibrated numbers, bit for bit)
            return DelayPrediction(
                actuation_mean=am,
                actuation_std=math.sqrt(ca2 * (av + an)),
                response_mean=rm,
                response_std=math.sqrt(cr2 * (rv + rn)),
                actuation_latent_std=math.sqrt(ca2 * av + (ca2 - 1.0) * an),
                response_latent_std=math.sqrt(cr2 * rv + (cr2 - 1.0) * rn),
            )
        out = self.predict_many(
            joint,
            direction,
            np.asarray(q, dtype=float)[None, :],
            t_s=t_s,
            method=method,
            combined=combined,
        )
        return DelayPrediction(*(float(v[0]) for v in out))

    def pinned(self) -> BlasPin:
        """Context manager holding BLAS at one thread while a control loop queries the model.

        :meth:`predict` pins BLAS around each call and restores it afterwards (a few µs, and
        OpenBLAS's threads wake to the restored count); holding the pin for the loop skips
        both. On the shared two-vCPU VM (load 0.7-1.0, five paired runs of 20,000-30,000
        queries) the p99 was 77-111 µs held against 90-162 µs per call: a modest gain,
        inside this machine's run-to-run noise (``benchmarks/bench_learning_predict.py``
        prints both).
        :class:`~timedexec.execution.TimedExecutor` holds it while connected.

        Examples
        --------
        >>> with model.pinned():                                   # doctest: +SKIP
        ...     while running:
        ...         p = model.predict(joint=2, direction=1, q=q)
        """
        return BLAS_PIN

    def check_thermal_state(self, t_since_power_on_s: float) -> str | None:
        """Whether this model answers for a robot ``t_since_power_on_s`` after power-on:
        None if so (or the bundle does not know its thermal state), else why not, also
        warned as a :class:`~timedexec.errors.ThermalStateWarning` (every call: this is the
        check a caller makes once, e.g. before an executor starts; ``predict`` warns once
        per model by itself)."""
        why = thermal_mismatch(self.thermal_state, [float(t_since_power_on_s)])
        if why is not None:
            warnings.warn(why, ThermalStateWarning, stacklevel=2)
        return why

    @property
    def thermal_clock(self) -> bool:
        """Whether ``t_s`` is the time since the robot's power-on (the bundle knows the
        thermal states it was trained in), so that every bundle takes it."""
        return bool(self.thermal_state) and self.thermal_state.get("clock") == "power-on"  # type: ignore[union-attr]

    def _time_h(self, t_s: Any) -> Any:
        """The time input (hours) of a query: ``t_s`` (default: the end of the sweep),
        checked against the thermal states of the training (a warning when another)."""
        if t_s is not None:
            if not self.time_input and not self.thermal_clock:
                raise ConfigError(
                    "this bundle has no time input (trained without --time-input) and no "
                    "thermal clock (its table had no t_since_power_on); drop t_s"
                )
            t = np.asarray(t_s, dtype=float)
            if not np.all(np.isfinite(t)):
                raise ConfigError(f"t_s={t_s!r}: the time must be finite seconds")
            if not self._thermal_warned:
                why = thermal_mismatch(self.thermal_state, t)
                if why is not None:
                    self._thermal_warned = True  # once per model: a control loop asks often
                    warnings.warn(why, ThermalStateWarning, stacklevel=4)
        if not self.time_input:
            return None
        if t_s is None:
            return self.time_default_s / 3600.0  # type: ignore[operator]
        return t / 3600.0

    def _encode_one(
        self, joint: int, direction: int, q: ArrayLike, combined: bool, t_s: float | None = None
    ) -> FloatArray:
        qa = np.asarray(q, dtype=float)
        if qa.shape != (6,):
            raise ConfigError(f"q must hold 6 joint angles (rad), got shape {qa.shape}")
        if not math.isfinite(float(qa.sum())):
            bad = int(np.flatnonzero(~np.isfinite(qa))[0])
            raise ConfigError(f"q{bad + 1} is {qa[bad]}; joint angles must be finite (rad)")
        if direction != 1 and direction != -1:
            raise ConfigError(f"direction {direction!r} must be +1 or -1")
        n_hot = len(self.joints) if combined else 0
        x = np.empty(13 + n_hot + (1 if self.time_input else 0))
        x[0:12:2] = np.sin(qa)
        x[1:12:2] = np.cos(qa)
        x[12] = direction
        if combined:
            x[13 : 13 + n_hot] = [1.0 if j == joint else 0.0 for j in self.joints]
        t_h = self._time_h(t_s) if self.time_input or t_s is not None else None
        if t_h is not None:
            x[-1] = float(t_h)
        return x

    def predict_many(
        self,
        joint: ArrayLike,
        direction: ArrayLike,
        q: ArrayLike,
        *,
        t_s: ArrayLike | None = None,
        method: str | None = None,
        combined: bool = False,
    ) -> DelayPrediction:
        """Vectorised :meth:`predict`: joints, directions (and times) scalars or (n,), q (n, 6).

        Returns
        -------
        DelayPrediction
            Arrays of shape (n,), s.
        """
        if method is None:
            method = self.default_method
        self._method(method)
        qa = np.asarray(q, dtype=float)
        if qa.ndim != 2 or qa.shape[1] != 6:
            raise ConfigError(f"q must have shape (n, 6) (rad), got {qa.shape}")
        n = len(qa)
        bad = ~np.isfinite(qa)
        if bad.any():
            row, col = (int(v) for v in np.argwhere(bad)[0])
            raise ConfigError(
                f"q row {row}: q{col + 1} is {qa[row, col]}; joint angles must be finite"
            )
        dirs = np.broadcast_to(np.asarray(direction), (n,))
        okd = (dirs == 1) | (dirs == -1)
        if not okd.all():
            row = int(np.flatnonzero(~okd)[0])
            raise ConfigError(f"row {row}: direction {dirs[row]!r} must be +1 or -1")
        joints = np.broadcast_to(np.asarray(joint), (n,))
        t_h = self._time_h(t_s)
        t_all = None if t_h is None else np.broadcast_to(np.asarray(t_h, dtype=float), (n,))
        out = {
            f"{d}_{k}": np.full(n, np.nan)
            for d in ("actuation", "response")
            for k in ("mean", "std", "latent_std")
        }
        for j in np.unique(joints):
            key = self._key(int(j), combined)
            rows = np.flatnonzero(joints == j)
            t_rows = None if t_all is None else t_all[rows]
            if key == "combined":
                X = encode_inputs(qa[rows], dirs[rows], joints[rows], self.joints, t_h=t_rows)
            else:
                X = encode_inputs(qa[rows], dirs[rows], t_h=t_rows)
            for delay in _DELAYS:
                short = delay.split("_")[0]
                pred = self._predictor(method, delay, key)
                mean, var = pred.predict(X)
                out[f"{short}_mean"][rows] = mean
                if var is not None:
                    c2 = self._scale(method, delay, key) ** 2
                    noise = pred.noise_var_s2  # type: ignore[attr-defined]
                    out[f"{short}_std"][rows] = np.sqrt(c2 * (var + noise))
                    out[f"{short}_latent_std"][rows] = np.sqrt(c2 * var + (c2 - 1.0) * noise)
                else:
                    out[f"{short}_std"][rows] = self._trial_std(method, delay, key)
        return DelayPrediction(**out)

    def gp_predictor(self, delay: str, joint: int | None = None) -> GPPredictor:
        """The GP predictor of ``delay`` for ``joint`` (None: the combined model).

        The raw GP: its latent variance and ``noise_var_s2`` are uncalibrated. For the
        trial std that :meth:`predict` reports, multiply ``sqrt(var + noise_var_s2)`` by
        :meth:`gp_std_scale` of the same delay and model.
        """
        key = "combined" if joint is None else self._key(joint, False)
        return self._predictor("gpr", delay, key)  # type: ignore[return-value]

    def gp_std_scale(self, delay: str, joint: int | None = None) -> float:
        """Calibration factor (>= 1) of the GP's trial std for ``delay`` and ``joint``.

        From the training's cross-validation (``std_scale`` in the manifest, see
        docs/models.md); 1.0 for bundles without it. ``joint=None``: the combined model.
        """
        if delay not in _DELAYS:
            raise ConfigError(f"delay {delay!r} must be one of {', '.join(_DELAYS)}")
        key = "combined" if joint is None else self._key(joint, False)
        return self._scale(CALIBRATED_METHOD, delay, key)

    def bound_z(self, delay: str, joint: int | None = None, method: str | None = None) -> float:
        """Half-width of ``method``'s 95 % prediction bound, in its (calibrated) trial stds.

        For the GP of a bundle trained with cross-validation: the split-conformal quantile
        of its held-out ``|y - mean| / std`` (``bound_z`` in the manifest,
        :func:`~timedexec.learning.bound_quantile`; about 1.65 where the controller cycle's
        uniform wait dominates the scatter). Otherwise, and for bundles from before it was
        stored, the Gaussian 1.959964. ``joint=None``: the combined model.
        """
        if delay not in _DELAYS:
            raise ConfigError(f"delay {delay!r} must be one of {', '.join(_DELAYS)}")
        method = self.default_method if method is None else method
        key = "combined" if joint is None else self._key(joint, False)
        return self._bound_z(method, delay, key)

    def _bound_z(self, method: str, delay: str, key: str) -> float:
        """``bound_z`` of the calibrated method (the Gaussian 1.96 without one)."""
        calibration = self.manifest.get("std_calibration") or {}
        if method != calibration.get("method", CALIBRATED_METHOD):
            return GAUSSIAN_Z95
        return self._bound_z_table.get(delay, {}).get(key, GAUSSIAN_Z95)

    def predict_bounds(
        self,
        joint: ArrayLike,
        direction: ArrayLike,
        q: ArrayLike,
        *,
        t_s: ArrayLike | None = None,
        method: str | None = None,
        combined: bool = False,
    ) -> DelayBounds:
        """95 % prediction bounds of single future trials' delays, s (vectorised).

        ``mean ± z · std`` of :meth:`predict_many` with ``z`` = :meth:`bound_z` of each
        row's delay and model: for a GP trained with cross-validation, an interval that
        held on 95 % of the held-out trials of new configurations in training (its width
        from the cycle's short-tailed scatter, not a Gaussian's); otherwise the Gaussian
        ``mean ± 1.96 std``. Arguments as :meth:`predict_many`. For execution, whose bounds
        add the cycle wait to a Gaussian themselves, see
        :class:`~timedexec.execution.TimingBounds`.

        Returns
        -------
        DelayBounds
            Arrays of shape (n,), s.
        """
        if method is None:
            method = self.default_method
        p = self.predict_many(joint, direction, q, t_s=t_s, method=method, combined=combined)
        joints = np.broadcast_to(np.asarray(joint), p.actuation_mean.shape)
        half = {}
        for short, delay in (("actuation", "actuation_delay"), ("response", "response_delay")):
            z = np.empty(len(joints))
            for j in np.unique(joints):
                z[joints == j] = self._bound_z(method, delay, self._key(int(j), combined))
            half[short] = z * getattr(p, f"{short}_std")
        return DelayBounds(
            actuation_lower_s=p.actuation_mean - half["actuation"],
            actuation_upper_s=p.actuation_mean + half["actuation"],
            response_lower_s=p.response_mean - half["response"],
            response_upper_s=p.response_mean + half["response"],
        )

    def _scale(self, method: str, delay: str, key: str) -> float:
        """The calibration factor of ``method``'s std (1.0: none; only the GP has one)."""
        calibration = self.manifest.get("std_calibration") or {}
        if method != calibration.get("method", CALIBRATED_METHOD):
            return 1.0
        return self.std_scale.get(delay, {}).get(key, 1.0)

    def __repr__(self) -> str:
        return (
            f"DelayModel(robot={self.robot!r}, period_s={self.period_s}, joints={self.joints}, "
            f"methods={self.methods})"
        )
