"""Which backend ``arch: auto`` runs on, and why.

Taichi's own ``auto`` takes the first backend that starts: CUDA, then
Vulkan, then Metal, then the CPU. On Linux without a discrete GPU, Vulkan
often starts on Mesa's software rasterizer (lavapipe, reported as
``llvmpipe``) or on SwiftShader: a Vulkan *device* that runs on the CPU
through a graphics driver. There, rope_hang took 73 ms a frame against
8.7 ms on the CPU backend (docs/benchmarks.md, "Backend"). So ``auto``
asks the drivers first, without starting Taichi:

- CUDA: the driver library is loaded and asked for its device count.
- Vulkan: an instance is created and its physical devices listed with
  their type; a device of type CPU is software. Vulkan is a candidate only
  if a hardware device (discrete, integrated or virtual GPU) is listed,
  and Taichi is pointed at the best one (``TI_VISIBLE_DEVICE``, unless the
  user set it).
- Metal: on macOS, always hardware.

Every probe is a few driver calls through ``ctypes`` (milliseconds) and
fails soft: a missing or broken driver counts as no device.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
from dataclasses import dataclass

# VkPhysicalDeviceType
VK_TYPE_NAMES = {0: "other", 1: "integrated GPU", 2: "discrete GPU", 3: "virtual GPU", 4: "CPU"}
_VK_HARDWARE_RANK = {2: 0, 1: 1, 3: 2}  # best first; 0 (other) and 4 (CPU) are not hardware GPUs
_VK_PROPERTIES_BYTES = 4096  # VkPhysicalDeviceProperties is 824 bytes on x86-64; room to spare
_VK_NAME_OFFSET, _VK_TYPE_OFFSET, _VK_NAME_BYTES = 20, 16, 256


@dataclass(frozen=True)
class VulkanDevice:
    """One Vulkan physical device as the loader lists it (``index`` is its place in that list)."""

    index: int
    name: str
    type: int

    @property
    def hardware(self) -> bool:
        return self.type in _VK_HARDWARE_RANK

    def describe(self) -> str:
        return f"{self.name} ({VK_TYPE_NAMES.get(self.type, 'unknown')})"


class _VkApplicationInfo(ctypes.Structure):
    _fields_ = [("sType", ctypes.c_int), ("pNext", ctypes.c_void_p), ("pApplicationName", ctypes.c_char_p),
                ("applicationVersion", ctypes.c_uint32), ("pEngineName", ctypes.c_char_p),
                ("engineVersion", ctypes.c_uint32), ("apiVersion", ctypes.c_uint32)]


class _VkInstanceCreateInfo(ctypes.Structure):
    _fields_ = [("sType", ctypes.c_int), ("pNext", ctypes.c_void_p), ("flags", ctypes.c_uint32),
                ("pApplicationInfo", ctypes.POINTER(_VkApplicationInfo)), ("enabledLayerCount", ctypes.c_uint32),
                ("ppEnabledLayerNames", ctypes.c_void_p), ("enabledExtensionCount", ctypes.c_uint32),
                ("ppEnabledExtensionNames", ctypes.c_void_p)]


def _load(names: list[str]):
    for name in names:
        if not name:
            continue
        try:
            return ctypes.CDLL(name)
        except OSError:
            continue
    return None


def parse_vk_properties(raw: bytes) -> tuple[str, int]:
    """The device name and type from the bytes of a ``VkPhysicalDeviceProperties``."""
    dev_type = int.from_bytes(raw[_VK_TYPE_OFFSET:_VK_TYPE_OFFSET + 4], sys.byteorder)
    name = raw[_VK_NAME_OFFSET:_VK_NAME_OFFSET + _VK_NAME_BYTES].split(b"\0", 1)[0].decode("utf-8", "replace")
    return name, dev_type


def vulkan_devices() -> list[VulkanDevice]:
    """The Vulkan physical devices the loader lists; empty without a loader, a driver or a device."""
    lib = _load(["libvulkan.so.1", "libvulkan.1.dylib", "vulkan-1.dll", ctypes.util.find_library("vulkan") or ""])
    if lib is None:
        return []
    try:
        app = _VkApplicationInfo(0, None, b"sandbox-probe", 1, b"sandbox", 1, (1 << 22))  # VK_API_VERSION_1_0
        info = _VkInstanceCreateInfo(1, None, 0, ctypes.pointer(app), 0, None, 0, None)
        instance = ctypes.c_void_p()
        lib.vkCreateInstance.restype = ctypes.c_int
        if lib.vkCreateInstance(ctypes.byref(info), None, ctypes.byref(instance)) != 0:
            return []
        try:
            count = ctypes.c_uint32(0)
            lib.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), None)
            handles = (ctypes.c_void_p * count.value)()
            if count.value:
                lib.vkEnumeratePhysicalDevices(instance, ctypes.byref(count), handles)
            found = []
            for i in range(count.value):
                raw = ctypes.create_string_buffer(_VK_PROPERTIES_BYTES)
                lib.vkGetPhysicalDeviceProperties(ctypes.c_void_p(handles[i]), raw)
                name, dev_type = parse_vk_properties(raw.raw)
                found.append(VulkanDevice(i, name, dev_type))
            return found
        finally:
            lib.vkDestroyInstance(instance, None)
    except (AttributeError, OSError, ValueError):
        return []


def cuda_device_count() -> int:
    """How many CUDA devices the driver reports (0 without a driver)."""
    lib = _load(["libcuda.so.1", "libcuda.so", "nvcuda.dll"])
    if lib is None:
        return 0
    try:
        if lib.cuInit(0) != 0:
            return 0
        n = ctypes.c_int(0)
        return n.value if lib.cuDeviceGetCount(ctypes.byref(n)) == 0 else 0
    except (AttributeError, OSError):
        return 0


@dataclass(frozen=True)
class Choice:
    """The backends ``auto`` hands Taichi, best first (the CPU last), why, and the Vulkan device to use."""

    candidates: tuple[str, ...]
    reason: str
    vulkan_device: int | None = None


def choose_auto(*, cuda: int | None = None, vulkan: list[VulkanDevice] | None = None,
                platform: str | None = None) -> Choice:
    """What ``arch: auto`` tries, in order, from what the drivers report (probed unless given)."""
    cuda = cuda_device_count() if cuda is None else cuda
    vulkan = vulkan_devices() if vulkan is None else vulkan
    platform = sys.platform if platform is None else platform
    if cuda > 0:
        return Choice(("cuda", "cpu"), f"auto: {cuda} CUDA device(s)")
    hardware = sorted((d for d in vulkan if d.hardware), key=lambda d: (_VK_HARDWARE_RANK[d.type], d.index))
    if hardware:
        best = hardware[0]
        return Choice(("vulkan", "cpu"), f"auto: no CUDA device; Vulkan on {best.describe()}", best.index)
    if platform == "darwin":
        return Choice(("metal", "cpu"), "auto: macOS; Metal")
    if vulkan:
        listed = ", ".join(d.describe() for d in vulkan)
        return Choice(("cpu",), f"auto: no CUDA device; Vulkan lists only software devices ({listed}), "
                                "slower than the CPU backend; CPU")
    return Choice(("cpu",), "auto: no CUDA or Vulkan GPU; CPU")


def point_taichi_at(choice: Choice) -> None:
    """Have Taichi's Vulkan backend open the chosen device (a user's own ``TI_VISIBLE_DEVICE`` wins)."""
    if choice.vulkan_device is not None and "TI_VISIBLE_DEVICE" not in os.environ:
        os.environ["TI_VISIBLE_DEVICE"] = str(choice.vulkan_device)
