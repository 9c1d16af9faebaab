"""The image anomaly detector: models (a CPU-sized CNN, or the paper's EfficientNet-B0)
and the `AnomalyDetector` LeafSystem. Class 1 = anomalous (leads to failure)."""

import copy
import dataclasses as dc
from typing import List

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem
from pydrake.systems.sensors import ImageRgba8U
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from .bounds import bounded, check_bounds
from .checks import short
from .frame_worker import add_frame_worker
from .torch_threads import one_torch_thread


@dc.dataclass
class DetectorConfig:
    """Architecture and input size (pixels). ``small_cnn`` is the CPU default;
    `DetectorConfig.paper()` is EfficientNet-B0 at 224x224 (the paper)."""
    arch: str = "small_cnn"
    height: int = bounded(96, 16, 1024, whole=True, unit="px")
    width: int = bounded(160, 16, 1024, whole=True, unit="px")
    channels: List[int] = bounded(default_factory=lambda: [16, 32, 64, 96], low=1, high=1024,
                                  whole=True, each=True, items=(1, 8))
    stem_stride: int = bounded(1, 1, 2, whole=True)

    @classmethod
    def paper(cls) -> "DetectorConfig":
        return cls(arch="efficientnet_b0", height=224, width=224)

    def validate(self, where="detector.detector"):
        if self.arch not in ("small_cnn", "efficientnet_b0"):
            raise ValueError(f"{where}.arch must be small_cnn or efficientnet_b0, got "
                             f"{short(self.arch)}")
        return check_bounds(self, f"{where}.")


def resize_for_detector(images: np.ndarray, config: DetectorConfig) -> np.ndarray:
    """uint8 RGB ``(N, H, W, 3)`` or RGBA ``(N, H, W, 4)`` (alpha dropped) ->
    RGB ``(N, height, width, 3)`` with OpenCV's area filter: how datasets store their
    images, so training and the online loop see the same pixels. An RGBA camera frame
    goes in as it is: OpenCV drops alpha in ~0.01 ms, where numpy's strided
    ``[..., :3]`` copy of a 200x360 frame costs ~0.2 ms, as much as the resize."""
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise ValueError(f"the detector expects RGB or RGBA images shaped (N, H, W, 3|4), "
                         f"got {images.shape}")
    size = (config.width, config.height)
    if images.shape[1:] == (config.height, config.width, 3):
        return np.ascontiguousarray(images)                  # dataset images: stored resized

    def one(im):
        im = cv2.cvtColor(im, cv2.COLOR_RGBA2RGB) if im.shape[-1] == 4 else im
        if im.shape[:2] == (config.height, config.width):
            return np.ascontiguousarray(im)
        return cv2.resize(np.ascontiguousarray(im), size, interpolation=cv2.INTER_AREA)

    return np.stack([one(im) for im in images])


def flags_at(scores, threshold: float) -> np.ndarray:
    """Where a monitor flags (bools, ``scores``' shape): ``score >= threshold``, and
    where the score is not a number (a NaN signal or weight, which compares false with
    every threshold and would never flag: a monitor that cannot tell hands control
    over). The online port (`flag_of`), the guard's table rollouts and the offline
    judgement all flag by it."""
    return ~(np.asarray(scores, float) < threshold)


def flag_of(score: float, threshold: float) -> float:
    """A monitor's ``anomaly`` output of one score: 1.0 where it flags (`flags_at`),
    else 0.0."""
    return 1.0 if flags_at(score, threshold) else 0.0


def check_trained_size(rgba, image_size, system: str, what: str) -> None:
    """A ValueError in one line when the camera frame ``rgba`` (height first) is not
    ``image_size``, the size the monitor ``system`` (a ``what``) was trained on; None:
    any size."""
    if image_size is not None and rgba.shape[:2] != tuple(image_size):
        raise ValueError(f"{system}: input port 'color_image' got a {rgba.shape[0]}x"
                         f"{rgba.shape[1]} image, but this {what} was trained on "
                         f"{image_size[0]}x{image_size[1]} (height x width)")


def detector_input(images: torch.Tensor, config: DetectorConfig) -> torch.Tensor:
    """uint8 ``(N, H, W, 3)`` RGB -> float ``(N, 3, height, width)``, normalised with
    mean = std = 0.5 (the authors' transform)."""
    if images.dim() != 4 or images.shape[-1] != 3:
        raise ValueError(f"the detector expects RGB images shaped (N, H, W, 3), got "
                         f"{tuple(images.shape)}")
    x = images.permute(0, 3, 1, 2).float() / 255.0
    if tuple(x.shape[-2:]) != (config.height, config.width):
        x = F.interpolate(x, size=(config.height, config.width), mode="bilinear",
                          align_corners=False, antialias=True)
    return (x - 0.5) / 0.5


class SmallDetectorCNN(nn.Module):
    """Conv-BN-ReLU-pool stacks, global average pool, 2-way linear head. With
    ``stem_stride=2`` the first convolution strides 2, so every later layer works on a
    quarter of the pixels (a quarter of the cost) while the first still sees them all."""

    def __init__(self, config: DetectorConfig):
        super().__init__()
        layers, c = [], 3
        for i, out in enumerate(config.channels):
            stride = config.stem_stride if i == 0 else 1
            layers += [nn.Conv2d(c, out, 3, stride=stride, padding=1, bias=False),
                       nn.BatchNorm2d(out), nn.ReLU(inplace=True), nn.MaxPool2d(2)]
            c = out
        self.features = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Dropout(0.2), nn.Linear(c, 2))

    def forward(self, x):
        return self.head(self.features(x).mean(dim=(2, 3)))


def build_detector(config: DetectorConfig, pretrained_path: str = "") -> nn.Module:
    """A detector returning logits ``(N, 2)``. For EfficientNet-B0, ImageNet weights
    load from ``pretrained_path`` (a torchvision ``state_dict`` file) when given;
    nothing is ever downloaded."""
    config.validate()
    if config.arch == "small_cnn":
        if pretrained_path:
            raise ValueError("pretrained weights apply to efficientnet_b0 only")
        return SmallDetectorCNN(config)
    from torchvision.models import efficientnet_b0
    model = efficientnet_b0(weights=None)
    if pretrained_path:
        try:
            state = torch.load(pretrained_path, map_location="cpu", weights_only=True)
            model.load_state_dict(state)
        except Exception as e:
            raise ValueError(f"could not load EfficientNet-B0 ImageNet weights from "
                             f"{pretrained_path}: {type(e).__name__}: {str(e)[:200]}") from None
    model.classifier[1] = nn.Linear(model.classifier[1].in_features, 2)
    return model


class OneDnnConv2d(nn.Conv2d):
    """A ``Conv2d`` whose float CPU forward always runs oneDNN's kernel
    (``torch.mkldnn_convolution``), the one PyTorch picks for a batch. For one small
    frame PyTorch's heuristic picks its reference kernel instead (``_slow_conv2d_forward``:
    a 3x3 convolution whose input has at most 20,480 numbers, as every layer of a
    48x80 monitor's encoder has), which is slower and rounds differently from the batch
    that computed the same frame offline. Elsewhere (another device or type, no oneDNN,
    string padding, a padding mode other than zeros) it is the ``Conv2d`` it was."""

    def _conv_forward(self, input, weight, bias):
        if (input.device.type == "cpu" and input.dtype == torch.float32
                and self.padding_mode == "zeros" and not isinstance(self.padding, str)
                and torch.backends.mkldnn.is_available()):
            return torch.mkldnn_convolution(input, weight, bias, self.padding, self.stride,
                                            self.dilation, self.groups)
        return super()._conv_forward(input, weight, bias)


def inference_model(model: nn.Module) -> nn.Module:
    """A copy of ``model`` for per-frame CPU inference: eval mode; every ``Conv2d``
    directly followed by a ``BatchNorm2d`` inside an ``nn.Sequential`` folded into one
    convolution (the same function up to float rounding); weights in channels-last
    layout, which is how a camera frame permuted to NCHW already lies in memory; every
    ``Conv2d`` an `OneDnnConv2d`, so one frame takes the kernel a batch takes.
    Measured on the default detector: 0.73 -> 0.59 ms a frame from the first two
    (benchmarks/detector.py); on the 48x80 single-frame monitor's encoder, 0.50-0.52 ->
    0.36-0.41 ms from the third."""
    model = copy.deepcopy(model).eval()
    for module in list(model.modules()):
        if not isinstance(module, nn.Sequential):
            continue
        names = list(module._modules)
        for a, b in zip(names, names[1:]):
            conv, bn = module._modules[a], module._modules[b]
            if (isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d)
                    and bn.track_running_stats and bn.running_mean is not None):
                module._modules[a] = fuse_conv_bn_eval(conv, bn)
                module._modules[b] = nn.Identity()
    for module in model.modules():
        if type(module) is nn.Conv2d:
            module.__class__ = OneDnnConv2d            # the same parameters and state dict
    return model.to(memory_format=torch.channels_last)


def anomaly_probabilities(model: nn.Module, config: DetectorConfig, images_rgb: np.ndarray,
                          batch: int = 64) -> np.ndarray:
    """Anomaly probabilities (float64) of uint8 RGB ``(N, H, W, 3)`` or RGBA
    ``(N, H, W, 4)`` images by ``model`` (`AnomalyDetector.scores`)."""
    out = []
    with torch.no_grad():
        for i in range(0, len(images_rgb), batch):
            x = detector_input(torch.from_numpy(resize_for_detector(images_rgb[i:i + batch],
                                                                     config)), config)
            out.append(torch.softmax(model(x), dim=1)[:, 1].double().numpy())
    return np.concatenate(out) if out else np.zeros(0)


class DetectorFrameScore:
    """An `AnomalyDetector`'s work on one camera frame, picklable (`FrameWorker` runs it
    in a process of its own): uint8 ``(H, W, 3|4)`` -> its score ``(1,)``, on one torch
    thread, in this process as in that one (the same numbers)."""

    def __init__(self, model: nn.Module, config: DetectorConfig):
        self._model, self._config = model, config

    def __call__(self, rgba: np.ndarray) -> np.ndarray:
        with one_torch_thread():
            return anomaly_probabilities(self._model, self._config, rgba[None])


class AnomalyDetector(LeafSystem):
    """Flags camera images that lead to system failure.

    .. pydrake_system::

        name: AnomalyDetector
        input_ports:
        - color_image
        output_ports:
        - anomaly
        - score

    ``score`` is the probability of class 1 (anomalous); ``anomaly`` is 1.0 when
    ``score >= threshold`` or the score is NaN (`flag_of`), else 0.0.
    ``image_size = (height, width)``, when given, is enforced. ``encoder_process=True``
    scores each frame in a process of its own (`FrameWorker`), begun at each tick's
    publish event (every ``period`` s, the control period) when the frame is rendered,
    beside the loop's controller, as `HistoryMonitor`'s does; it scores on one torch
    thread then (in the loop too, should the process not answer), where the loop
    otherwise scores on torch's count.
    """

    def __init__(self, *, model: nn.Module, config: DetectorConfig, threshold: float = 0.5,
                 image_size=None, encoder_process: bool = False, period: float = None):
        super().__init__()
        if not 0.0 <= threshold <= 1.0:
            raise ValueError(f"AnomalyDetector: threshold must be in [0, 1], got {threshold}")
        self._model = inference_model(model)
        self._config = config.validate()
        self._threshold = float(threshold)
        self._image_size = tuple(image_size) if image_size is not None else None
        self._image_port = self.DeclareAbstractInputPort(
            "color_image", AbstractValue.Make(ImageRgba8U()))
        self._anomaly_port = self.DeclareVectorOutputPort("anomaly", 1, self._calc_anomaly)
        self._score_port = self.DeclareVectorOutputPort("score", 1, self._calc_score)
        self._worker = None
        if encoder_process:
            if period is None or not (np.isfinite(period) and period > 0):
                raise ValueError(f"AnomalyDetector: encoder_process needs the control "
                                 f"period > 0 s, got {period}")
            self._worker = add_frame_worker(
                self, work=DetectorFrameScore(self._model, self._config),
                image_port=self._image_port, period=period, name="AnomalyDetector")

    @property
    def threshold(self) -> float:
        return self._threshold

    def get_color_image_input_port(self):
        return self._image_port

    def get_anomaly_output_port(self):
        return self._anomaly_port

    def get_score_output_port(self):
        return self._score_port

    def scores(self, images_rgb: np.ndarray, batch: int = 64) -> np.ndarray:
        """Anomaly probabilities of uint8 RGB ``(N, H, W, 3)`` or RGBA
        ``(N, H, W, 4)`` images (`anomaly_probabilities`)."""
        return anomaly_probabilities(self._model, self._config, images_rgb, batch)

    @property
    def frame_worker(self):
        """The `FrameWorker` of ``encoder_process=True``, else None."""
        return self._worker

    def _calc_score(self, context, output):
        rgba = self._image_port.Eval(context).data
        check_trained_size(rgba, self._image_size, "AnomalyDetector", "detector")
        output.SetAtIndex(0, (self.scores(rgba[None]) if self._worker is None
                              else self._worker.work(rgba))[0])

    def _calc_anomaly(self, context, output):
        output.SetAtIndex(0, flag_of(self._score_port.Eval(context)[0], self._threshold))
