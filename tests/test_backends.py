"""``arch: auto`` never runs on a software Vulkan device (``sandbox/backends.py``)."""

import sys

import pytest

from sandbox import backends
from sandbox.backends import Choice, VulkanDevice, choose_auto, parse_vk_properties

LLVMPIPE = VulkanDevice(0, "llvmpipe (LLVM 15.0.6, 256 bits)", 4)
SWIFTSHADER = VulkanDevice(1, "SwiftShader Device (Subzero)", 4)
INTEGRATED = VulkanDevice(1, "Intel(R) UHD Graphics 620", 1)
DISCRETE = VulkanDevice(2, "AMD Radeon RX 6800", 2)


@pytest.mark.parametrize("devices", [[LLVMPIPE], [LLVMPIPE, SWIFTSHADER]])
def test_software_vulkan_is_never_chosen_and_the_reason_names_it(devices):
    choice = choose_auto(cuda=0, vulkan=devices, platform="linux")
    assert choice.candidates == ("cpu",) and choice.vulkan_device is None
    assert "only software devices" in choice.reason and "llvmpipe" in choice.reason


def test_a_hardware_gpu_is_chosen_even_when_listed_after_a_software_one():
    choice = choose_auto(cuda=0, vulkan=[LLVMPIPE, INTEGRATED, DISCRETE], platform="linux")
    assert choice.candidates == ("vulkan", "cpu")
    assert choice.vulkan_device == 2 and "AMD Radeon" in choice.reason  # discrete before integrated
    assert choose_auto(cuda=0, vulkan=[LLVMPIPE, INTEGRATED], platform="linux").vulkan_device == 1


def test_cuda_first_metal_on_macos_and_the_cpu_without_any_gpu():
    assert choose_auto(cuda=2, vulkan=[DISCRETE], platform="linux").candidates == ("cuda", "cpu")
    assert choose_auto(cuda=0, vulkan=[], platform="darwin").candidates == ("metal", "cpu")
    none = choose_auto(cuda=0, vulkan=[], platform="linux")
    assert none.candidates == ("cpu",) and "no CUDA or Vulkan GPU" in none.reason


def test_device_properties_are_read_at_vulkans_offsets():
    """``VkPhysicalDeviceProperties``: apiVersion, driverVersion, vendorID, deviceID (4 bytes each), then
    deviceType (int32) and deviceName (char[256])."""
    raw = bytearray(824)
    raw[0:4] = (4206592).to_bytes(4, sys.byteorder)  # apiVersion 1.3
    raw[16:20] = (4).to_bytes(4, sys.byteorder)
    raw[20:20 + 8] = b"llvmpipe"
    assert parse_vk_properties(bytes(raw)) == ("llvmpipe", 4)


def test_probes_fail_soft_without_drivers(monkeypatch):
    monkeypatch.setattr(backends, "_load", lambda names: None)
    assert backends.vulkan_devices() == [] and backends.cuda_device_count() == 0
    assert choose_auto(platform="linux").candidates == ("cpu",)


def test_probes_on_this_machine_return_devices_of_known_types():
    """Whatever this machine has (often nothing): the probe answers, in milliseconds, without Taichi."""
    for d in backends.vulkan_devices():
        assert d.type in backends.VK_TYPE_NAMES and d.name
    assert backends.cuda_device_count() >= 0


def test_the_chosen_vulkan_device_is_passed_to_taichi_unless_the_user_chose(monkeypatch):
    monkeypatch.delenv("TI_VISIBLE_DEVICE", raising=False)
    backends.point_taichi_at(Choice(("vulkan", "cpu"), "", 2))
    assert backends.os.environ["TI_VISIBLE_DEVICE"] == "2"
    monkeypatch.setenv("TI_VISIBLE_DEVICE", "0")
    backends.point_taichi_at(Choice(("vulkan", "cpu"), "", 2))
    assert backends.os.environ["TI_VISIBLE_DEVICE"] == "0"


def test_a_broken_loader_counts_as_no_device(monkeypatch):
    class Broken:
        def __getattr__(self, name):
            raise AttributeError(name)

    monkeypatch.setattr(backends, "_load", lambda names: Broken())
    assert backends.vulkan_devices() == [] and backends.cuda_device_count() == 0


def test_benchmarks_record_why_their_backend_was_chosen():
    """``sandbox bench`` results name the backend and the reason for it next to the machine."""
    from sandbox import runtime
    from sandbox.bench import machine

    m = machine()
    assert m["arch"] == runtime.current_arch() and m["backend_reason"] == runtime.reason() == "requested cpu"
