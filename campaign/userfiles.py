"""Python files a user names on the command line or in campaign.yaml (``path/file.py:ClassName``):
an effect class, a cell's adapters. Each file is executed once per process (per modification
time), so every class named from one file comes from one module instance."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from campaign.errors import ConfigError

_FILE_MODULES: dict = {}


def load_user_module(path, what: str):
    """The module of the user's file ``path``, executed on first use; ``what`` prefixes the
    ConfigError line (missing file, or whatever executing it raised)."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{what}: no such file {p}")
    key = (str(p.resolve()), p.stat().st_mtime_ns)
    module = _FILE_MODULES.get(key)
    if module is None:
        mod_name = f"campaign_user_{p.stem if p.stem.isidentifier() else 'file'}_{abs(hash(key)):x}"
        loader_spec = importlib.util.spec_from_file_location(mod_name, p)
        module = importlib.util.module_from_spec(loader_spec)
        sys.modules[mod_name] = module
        try:
            loader_spec.loader.exec_module(module)
        except Exception as exc:  # the user's file: report it in one line, whatever it raised
            sys.modules.pop(mod_name, None)
            raise ConfigError(f"{what}: {p} failed to load ({exc.__class__.__name__}: {exc})") from None
        _FILE_MODULES[key] = module
    return module
