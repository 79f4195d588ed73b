"""What a job records of the GPU it ran on: the GPU's name among its tags (:func:`ablate.hardware.tags`) and its
peak memory in GiB (:func:`ablate.jobs.train.gpu_memory`); nothing of the kind on the CPU. The CUDA calls are stood
in for: CI has no GPU."""

from __future__ import annotations

import torch
from omegaconf import OmegaConf

from ablate import hardware
from ablate.jobs import train


def test_a_job_on_the_cpu_records_no_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "NVIDIA H200")
    cpu_job = OmegaConf.create({"trainer": {"accelerator": "cpu", "precision": "32-true", "threads": 1}})
    assert "gpu" not in hardware.tags(cpu_job)
    assert train.gpu_memory(torch.device("cpu")) == {}


def test_a_job_on_a_gpu_records_its_name_and_its_peak_memory_in_gib(monkeypatch):
    asked: list[torch.device] = []

    def reading(value: float):
        def read(device: torch.device) -> float:
            asked.append(device)
            return value

        return read

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "NVIDIA H200")
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", reading(3 * 2**30))
    monkeypatch.setattr(torch.cuda, "max_memory_reserved", reading(4.5 * 2**30))
    gpu_job = OmegaConf.create({"trainer": {"accelerator": "gpu", "precision": "bf16-mixed", "threads": 1}})
    assert hardware.tags(gpu_job)["gpu"] == "NVIDIA H200"
    assert train.gpu_memory(torch.device("cuda:1")) == {"gpu_peak_alloc_gib": 3.0, "gpu_peak_reserved_gib": 4.5}
    assert asked == [torch.device("cuda:1")] * 2
