"""Stage protocols: what each config group's ``_target_`` must provide.

A stage is any object built by :func:`nirspi_pipe.instantiate.build` from its group's config
(after the allow-list check of :mod:`nirspi_pipe.targets`) that has the method named here. Stages are pure with respect to their inputs: they never mutate them, they
take randomness only from the ``numpy.random.Generator`` they are handed, and they do not time
themselves (the runner in :mod:`nirspi_pipe.pipeline` does). Bookkeeping a stage wants in the
record goes into the ``info`` mapping of the dataclass it returns; physical quantities a source
used go into ``Acquisition.derived``. Both are for the record only: what a later stage needs
is a typed field (``Acquisition.medium``, ``PointCloud.depth_scale``/``depth_offset_m``). Problems that make a result meaningless are reported with
``warnings.warn``; the runner stores them in the record.

=========  ==============================================  ==========================
group      method                                          returns
=========  ==============================================  ==========================
scene      ``render(camera)``                              :class:`Scene`
source     ``acquire(scene, indices, n, rng)``             :class:`Acquisition`
scan       ``select(n)`` (``ratio`` attribute)             flat pattern indices
solver     ``solve(acquisition)``                          :class:`Image2D`
upscale    ``upscale(image)``                              :class:`Image2D`
sfs        ``solve(image, camera)``                        :class:`DepthMap`
itof       ``measure(scene, acquisition, rng)``            :class:`ItofSample`
fusion     ``fuse(depth, itof, camera)``                   :class:`PointCloud`
surface    ``reconstruct(cloud)``                          :class:`Mesh`
metrics    ``compute(products)``                           ``{name: float}``
=========  ==============================================  ==========================

The runner checks each stage it builds against its group's protocol (:func:`check_stage`: every
method and attribute the protocol declares, by name), so a stage that lacks a member the
pipeline uses fails when it is built, with one line naming the group, its ``_target_`` and the
missing members. Two optional protocols add what only some stages do: a source that replays a
recording naming its scan option (:class:`ReadsScanOptions`: the runner hands it the config
layer's resolver), an iToF stage whose spots are aimed with the 2D image (:class:`Aimable`) and
a metrics stage that scores with the run's own built stages (:class:`ScoresWithStages`: the
runner hands it the scene model, source and upscaler it built, :class:`RunStages`; no config
copy of them is built a second time). The runner reads no member that a protocol does not declare.

Every stage class (and every class built inside a stage's node, such as a fog model) may also
define :class:`WarmsUp`'s class method ``warm_up(params)``: what its first use in a process
would otherwise pay for (imports, compiled kernels loaded from their disk cache). The sweep
launcher calls it through :func:`nirspi_pipe.execute.warm_up` once in the sweeping process,
before it forks the jobs, for every ``_target_`` the sweep's configs name; it names no module.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.types import (
    Acquisition,
    Camera,
    DepthMap,
    Image2D,
    ItofSample,
    Mesh,
    PointCloud,
    Scene,
)

__all__ = [
    "SceneModel",
    "Source",
    "ScanOrder",
    "Solver",
    "Upscaler",
    "ShapeFromShading",
    "NeedsScene",
    "Itof",
    "Fusion",
    "Surface",
    "Metrics",
    "Products",
    "WarmsUp",
    "ReadsScanOptions",
    "Aimable",
    "RunStages",
    "ScoresWithStages",
    "ScanIndices",
    "PROTOCOLS",
    "check_stage",
]

#: Resolves the scan option a recording names: ``(order, ratio, n) -> flat pattern indices``
#: (the config layer's :func:`nirspi_pipe.app.configs.scan_indices`).
ScanIndices = Callable[[str, float, int], np.ndarray]


@runtime_checkable
class WarmsUp(Protocol):
    """Optional part of every stage protocol: prepare this process for the stage.

    ``warm_up(params)`` is a class method: ``params`` are the keys of the stage's config node
    (``_target_`` and other ``_``-keys removed), and no instance is built, so a stage whose
    construction does per-process work (an OpenCL context) does not do it here. It is called
    in a process that then forks the jobs, so it must not start threads (no OpenCL platform or
    context: PoCL's worker threads would not exist in the children) and must not change state
    a job reads (it only makes the first call cheaper). It raises nothing the job would not
    raise itself: a failure is reported by :func:`nirspi_pipe.execute.warm_up` and the job
    that needs the stage says what is wrong.
    """

    @classmethod
    def warm_up(cls, params: Mapping[str, Any]) -> None: ...


@runtime_checkable
class SceneModel(Protocol):
    """Renders ground truth (geometry, reflectance, shading) for a camera."""

    def render(self, camera: Camera) -> Scene: ...


@runtime_checkable
class Source(Protocol):
    """Produces single-pixel measurements for the given pattern indices.

    ``scene`` is None when the source does not need one (``needs_scene`` False): a recorded file
    or a live device. A source may then ignore ``indices`` and return what was recorded.
    """

    needs_scene: bool

    def acquire(self, scene: Scene | None, indices: np.ndarray, n: int, rng: np.random.Generator) -> Acquisition: ...


@runtime_checkable
class ReadsScanOptions(Protocol):
    """A source whose input names its scan option (a recording's pattern spec ``order``): the
    runner hands it the config layer's resolver when it has none (``scan_indices`` is None)."""

    scan_indices: ScanIndices | None

    def with_scan_indices(self, resolver: ScanIndices | None) -> ReadsScanOptions: ...


@runtime_checkable
class ScanOrder(Protocol):
    """A scan order: a permutation of the ``n²`` pattern indices, truncated to ``ratio``."""

    ratio: float

    def order(self, n: int) -> np.ndarray: ...

    def select(self, n: int) -> np.ndarray: ...


@runtime_checkable
class Solver(Protocol):
    """Reconstructs an image (relative radiance) from an acquisition."""

    def solve(self, acquisition: Acquisition) -> Image2D: ...


@runtime_checkable
class Upscaler(Protocol):
    """Super-resolves a reconstructed image."""

    def upscale(self, image: Image2D) -> Image2D: ...


@runtime_checkable
class ShapeFromShading(Protocol):
    """Recovers depth from a shaded image."""

    def solve(self, image: Image2D, camera: Camera) -> DepthMap: ...


@runtime_checkable
class NeedsScene(Protocol):
    """Optional part of the SFS protocol: a stage that reads the rendered scene itself (the
    oracle ``sfs=truth``, :class:`~nirspi_pipe.sfs.oracle.TruthDepth`): the runner passes it the
    scene rendered for the SFS grid as ``solve(image, camera, scene)``."""

    needs_scene: bool


@runtime_checkable
class Itof(Protocol):
    """Measures the four iToF reference points.

    The iToF lasers look through the same medium as the single-pixel camera: the fog
    extinction and background light the source used are the typed ``acquisition.medium``
    (:class:`~nirspi_pipe.types.Medium`; clear and dark when the source does not know)."""

    def measure(self, scene: Scene | None, acquisition: Acquisition, rng: np.random.Generator) -> ItofSample: ...


@runtime_checkable
class Aimable(Protocol):
    """An iToF stage whose spots are steered with the 2D image: the runner measures with
    ``aimed(image, camera)`` (``camera``: the image's grid) instead of the stage itself."""

    def aimed(self, image: Image2D, camera: Camera) -> Itof: ...


@runtime_checkable
class Fusion(Protocol):
    """Fuses SFS depth with the iToF points into a metric point cloud."""

    def fuse(self, depth: DepthMap, itof: ItofSample | None, camera: Camera) -> PointCloud: ...


@runtime_checkable
class Surface(Protocol):
    """Builds a triangle mesh from a point cloud."""

    def reconstruct(self, cloud: PointCloud) -> Mesh: ...


@dataclass(frozen=True)
class Products:
    """Everything one run produced, handed to the metrics stage. Absent stages give None."""

    truth: Scene | None
    acquisition: Acquisition
    image: Image2D
    upscaled: Image2D | None = None
    depth: DepthMap | None = None
    itof: ItofSample | None = None
    cloud: PointCloud | None = None
    mesh: Mesh | None = None


@runtime_checkable
class Metrics(Protocol):
    """Scores a run's products against the ground truth."""

    def compute(self, products: Products) -> dict[str, float]: ...


@dataclass(frozen=True)
class RunStages:
    """The run's built stages that a metrics stage may score with (:class:`ScoresWithStages`);
    None where the run has none (``scene=null``, ``upscale=null``)."""

    scene: SceneModel | None = None
    source: Source | None = None
    upscaler: Upscaler | None = None


@runtime_checkable
class ScoresWithStages(Protocol):
    """Optional part of the metrics protocol: a metrics stage that scores with the run's own
    stages (the scene model rendered again on an upscaled grid, the source's noise-free image
    there, the upscaler applied to the camera's noise-free image). The runner builds each stage
    once and calls ``compute`` on ``with_stages(RunStages(scene, source, upscaler))``."""

    def with_stages(self, stages: RunStages) -> Metrics: ...


#: The protocol each stage group's ``_target_`` must satisfy.
PROTOCOLS: dict[str, type] = {
    "scene": SceneModel,
    "source": Source,
    "scan": ScanOrder,
    "solver": Solver,
    "upscale": Upscaler,
    "sfs": ShapeFromShading,
    "itof": Itof,
    "fusion": Fusion,
    "surface": Surface,
    "metrics": Metrics,
}


def protocol_members(protocol: type) -> list[str]:
    """The methods and attributes ``protocol`` declares (in declaration order)."""
    methods = [k for k, v in vars(protocol).items() if callable(v) and not k.startswith("_")]
    return [*vars(protocol).get("__annotations__", {}), *methods]


def check_stage(group: str, stage: Any, target: Any = None) -> None:
    """Raise :class:`ConfigError` (one line: ``group._target_``, the missing members) when the
    stage built for ``group`` lacks a member of its protocol (:data:`PROTOCOLS`)."""
    protocol = PROTOCOLS.get(group)
    if protocol is None:
        return
    missing = [m for m in protocol_members(protocol) if not hasattr(stage, m)]
    if missing:
        need = ", ".join(protocol_members(protocol))
        raise ConfigError(
            f"{group}._target_",
            target if target is not None else type(stage).__qualname__,
            f"a {group} stage with {need} (nirspi_pipe.stages.{protocol.__name__}); it lacks {', '.join(missing)}",
            absolute=True,
        )
