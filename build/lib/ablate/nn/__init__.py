"""Plain-torch building blocks: ResNet, YOLACT-style FPN, VGG-16 SSD trunk, U-Net blocks, local weight loading."""

from ablate.nn.fpn import FPN
from ablate.nn.resnet import ResNet
from ablate.nn.unet import ConvBlock, DecoderBlock, Encoder
from ablate.nn.vgg import VGG16SSD
from ablate.nn.weights import WeightsError, load_weights

__all__ = ["FPN", "ResNet", "ConvBlock", "DecoderBlock", "Encoder", "VGG16SSD", "WeightsError", "load_weights"]
