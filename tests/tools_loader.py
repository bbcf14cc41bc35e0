"""The scripts under tools/ are not a package: the tests load one by its file name."""
import importlib.util
from pathlib import Path

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def load_tool(name: str):
    """The module tools/NAME.py, loaded afresh (its top level run once more)."""
    spec = importlib.util.spec_from_file_location(f"packetrt_tool_{name}", TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
