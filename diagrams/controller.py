"""Vision controllers: what a closed loop needs from one, and how a run file names one.

A controller is any Drake `System` (a LeafSystem or a Diagram) with

- an abstract input port ``color_image`` (the wing camera's `ImageRgba8U`),
- a vector output port ``steering_angle`` of size 1 (rad, positive turns left),
- optionally a vector output port ``estimate`` (what it believes about the state,
  e.g. TaxiNet's ``[px_hat m, theta_hat deg]``; only the prediction-error baseline and
  the logs use it).

A run file names the function that builds it: ``controller: {factory:
"package.module:function"}`` (an importable module) or ``"path/to/file.py:function"``
(relative to the working directory), with ``parameters: {name: number, ...}`` for
it. The function takes the `ControllerConfig` and returns the System. An empty
``factory`` is TaxiNet followed by the P-controller (`make_taxinet_controller`).

A factory file may import the modules next to it, and its fingerprint covers every file
of its folder (`reachwatch.diagrams.user_code`)."""

import dataclasses as dc
import re

from pydrake.common.value import AbstractValue
from pydrake.systems.framework import Diagram, DiagramBuilder, PortDataType, System
from pydrake.systems.sensors import ImageRgba8U

from reachwatch.systems import ProportionalController, TaxiNet
from reachwatch.systems.checks import clip
from reachwatch.systems.files import local_copy

from . import user_code
from .user_errors import call_failure
from .checkpoints import REFERENCE_TAXINET, load_taxinet

IMAGE_INPUT = "color_image"
CONTROL_OUTPUT = "steering_angle"
ESTIMATE_OUTPUT = "estimate"


class TaxiNetController(Diagram):
    """TaxiNet (image -> estimate) followed by the P-controller (estimate -> steering).

    .. pydrake_system::

        name: TaxiNetController
        input_ports:
        - color_image
        output_ports:
        - steering_angle
        - estimate

    ``taxinet`` is the inner `TaxiNet` system (its ``estimate(images)`` runs a batch)."""

    def __init__(self, *, checkpoint: str = "", px_gain: float, theta_gain: float):
        super().__init__()
        model, preprocess_config, metadata = load_taxinet(checkpoint or REFERENCE_TAXINET)
        builder = DiagramBuilder()
        self.taxinet = builder.AddNamedSystem("taxinet", TaxiNet(
            model=model, preprocess_config=preprocess_config,
            image_size=metadata.get("image_size")))
        p_controller = builder.AddNamedSystem("p_controller", ProportionalController(
            px_gain=px_gain, theta_gain=theta_gain))
        builder.Connect(self.taxinet.get_estimate_output_port(),
                        p_controller.get_estimate_input_port())
        builder.ExportInput(self.taxinet.get_color_image_input_port(), IMAGE_INPUT)
        builder.ExportOutput(p_controller.get_steering_angle_output_port(), CONTROL_OUTPUT)
        builder.ExportOutput(self.taxinet.get_estimate_output_port(), ESTIMATE_OUTPUT)
        builder.BuildInto(self)
        self.set_name("taxinet_controller")

    def estimate(self, images_rgb):
        """``(N, H, W, 3)`` uint8 RGB -> ``(N, 2)`` estimates, as one batch."""
        return self.taxinet.estimate(images_rgb)


def make_taxinet_controller(config) -> TaxiNetController:
    """The reference controller: ``config.checkpoint`` (empty: the shipped TaxiNet) and
    the P-controller with ``config.px_gain`` and ``config.theta_gain``."""
    return TaxiNetController(checkpoint=config.checkpoint, px_gain=config.px_gain,
                             theta_gain=config.theta_gain)


def resolve_factory(spec: str):
    """The function a ``controller.factory`` string names (empty: TaxiNet's). A file's
    folder is importable while it loads and while the factory runs, as the folder of a
    script is: ``import helpers`` in it finds its ``helpers.py``."""
    return user_code.resolve(spec)[1] if spec else make_taxinet_controller


def check_controller(system, where="controller") -> System:
    """``system`` if it has the ports a controller needs; else a ValueError saying what
    is missing."""
    if not isinstance(system, System):
        raise ValueError(f"{where}: the factory must return a Drake System, got "
                         f"{type(system).__name__}")
    inputs = [system.get_input_port(i).get_name() for i in range(system.num_input_ports())]
    outputs = [system.get_output_port(i).get_name() for i in range(system.num_output_ports())]
    if IMAGE_INPUT not in inputs:
        raise ValueError(f"{where}: the system '{system.get_name()}' needs an input port "
                         f"'{IMAGE_INPUT}' (the camera's ImageRgba8U); it has {inputs}")
    port = system.GetInputPort(IMAGE_INPUT)
    if port.get_data_type() != PortDataType.kAbstractValued:
        raise ValueError(f"{where}: input '{IMAGE_INPUT}' must be abstract (ImageRgba8U)")
    if not isinstance(port.Allocate().get_value(), ImageRgba8U):
        raise ValueError(f"{where}: input '{IMAGE_INPUT}' must hold an ImageRgba8U")
    if CONTROL_OUTPUT not in outputs:
        raise ValueError(f"{where}: the system '{system.get_name()}' needs a vector output "
                         f"port '{CONTROL_OUTPUT}' of size 1 (rad); it has {outputs}")
    for name, size in ((CONTROL_OUTPUT, 1), (ESTIMATE_OUTPUT, None)):
        if name in outputs:
            port = system.GetOutputPort(name)
            if port.get_data_type() != PortDataType.kVectorValued or (
                    size is not None and port.size() != size):
                raise ValueError(f"{where}: output '{name}' must be a vector"
                                 f"{f' of size {size}' if size else ''}")
    return system


def make_controller(config) -> System:
    """The controller ``config`` (a `ControllerConfig`) names, built and checked. The
    factory is handed ``config.data_files`` as paths it can open where it runs (on a
    cluster's worker, the copies that came with the task: `local_copy`)."""
    where = f"controller.factory '{config.factory or 'TaxiNet'}'"
    module, factory = (user_code.resolve(config.factory) if config.factory
                       else (None, make_taxinet_controller))
    if config.data_files:       # on a cluster's worker, the copies that came with the task
        config = dc.replace(config, data_files=[local_copy(p) for p in config.data_files])
    try:
        with user_code.importable(module):
            system = factory(config)
    except TypeError as e:
        if not config.factory:
            raise
        raise parameter_error(where, config.parameters, e, factory) or ValueError(
            f"{where}: calling it with the ControllerConfig failed (TypeError: "
            f"{clip(e, 200)}); a factory takes the config and returns a Drake System") from e
    except ValueError:
        raise                                   # the factory's own one-line complaint
    except (Exception, SystemExit) as e:      # sys.exit(): was a silent exit
        if not config.factory:
            raise
        raise call_failure(config.factory, e, module) from e
    user_code.warn_unkeyed_reads(config.factory, module,
                                 keyed=[config.checkpoint, *config.data_files])
    return check_controller(system, where)


def parameter_error(where, parameters, error: TypeError, factory=None):
    """A ValueError naming the parameter when ``error`` is Python's complaint, about a
    call the function ``factory`` made itself (one that passes ``**config.parameters``
    on), of an unknown keyword argument that ``parameters`` holds or of missing
    arguments; else None."""
    code = getattr(factory, "__code__", None)
    last = error.__traceback__
    while last is not None and last.tb_next is not None:
        last = last.tb_next
    if code is not None and (last is None or last.tb_frame.f_code is not code):
        return None             # raised deeper down: not about the factory's parameters
    text = str(error)
    unknown = re.search(r"unexpected keyword argument '(\w+)'", text)
    if unknown and unknown.group(1) in parameters:
        return ValueError(f"{where}: controller.parameters.{unknown.group(1)} is not a "
                          f"parameter it takes (TypeError: {clip(text, 200)})")
    missing = re.search(r"missing \d+ required (?:positional |keyword-only )?arguments?: (.+)",
                        text)
    if missing:
        names = re.findall(r"'(\w+)'", missing.group(1))
        if names:
            return ValueError(f"{where}: controller.parameters lacks "
                              f"{', '.join(names)}, which it needs (TypeError: "
                              f"{clip(text, 200)})")
    return None


def has_estimate(system) -> bool:
    return system.HasOutputPort(ESTIMATE_OUTPUT)


def estimate_size(system) -> int:
    """How many numbers ``system``'s ``estimate`` output holds (0: it has none)."""
    return system.GetOutputPort(ESTIMATE_OUTPUT).size() if has_estimate(system) else 0


def image_value(rgb) -> AbstractValue:
    """An `ImageRgba8U` value holding ``rgb`` ``(H, W, 3 or 4)`` uint8 (alpha 255)."""
    height, width = rgb.shape[:2]
    image = ImageRgba8U(width, height)
    image.mutable_data[..., :3] = rgb[..., :3]
    image.mutable_data[..., 3] = 255
    return AbstractValue.Make(image)


class ControllerProbe:
    """Evaluates a controller on images outside any loop (datasets, baselines):
    fixes its image input and reads ``steering_angle`` and ``estimate``."""

    def __init__(self, system):
        self.system = system
        self.context = system.CreateDefaultContext()

    def outputs(self, rgb):
        """``(steering (1,), estimate (k,) or None)`` for one RGB image."""
        self.system.GetInputPort(IMAGE_INPUT).FixValue(self.context, image_value(rgb))
        steering = self.system.GetOutputPort(CONTROL_OUTPUT).Eval(self.context).copy()
        estimate = (self.system.GetOutputPort(ESTIMATE_OUTPUT).Eval(self.context).copy()
                    if has_estimate(self.system) else None)
        return steering, estimate
