"""Prelude for subprocess tests of the onboard side: make torch, onnx and dadiff.export unimportable."""

PRELUDE = '''
import importlib.abc
import sys

BLOCKED = ("torch", "onnx", "dadiff.export")


class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if any(name == b or name.startswith(b + ".") for b in BLOCKED):
            raise ImportError(f"{name} is not installed here (blocked by the test)")
        return None


sys.meta_path.insert(0, Blocker())
'''
