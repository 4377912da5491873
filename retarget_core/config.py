"""Library settings, read from the environment (prefix ``RETARGET_``). Every limit is named here."""

from __future__ import annotations

from functools import lru_cache

from pydantic_settings import BaseSettings, SettingsConfigDict


class CoreSettings(BaseSettings):
    """Limits and defaults of retarget_core. Override with e.g. ``RETARGET_MAX_FRAMES=20000``."""

    model_config = SettingsConfigDict(env_prefix="RETARGET_")

    max_file_bytes: int = 512 * 1024 * 1024
    max_frames: int = 100_000
    max_joints: int = 1_000
    max_vertices: int = 2_000_000
    max_triangles: int = 4_000_000
    max_accessor_elements: int = 50_000_000
    default_fps: float = 30.0
    fbx_timeout_seconds: float = 120.0
    fbx_memory_bytes: int = 4 * 1024 * 1024 * 1024
    assimp_command: str = "assimp"


@lru_cache(maxsize=1)
def get_settings() -> CoreSettings:
    """The process-wide settings (read once)."""
    return CoreSettings()
