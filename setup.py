"""The build step pyproject.toml cannot declare: after copying the package, compile the filter's
kernels into its numba cache (c3bf_gym/_precompile.py), so the installed package does not compile
them on first use. Skipped for editable installs, and with C3BF_GYM_PRECOMPILE=0; a failure here
is reported and does not fail the build (the kernels then compile on first use)."""

import os
import shutil
import subprocess
import sys

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildWithKernels(build_py):
    def run(self) -> None:
        # the wheel carries build_lib's whole tree (the cache included): a module deleted from the
        # sources, or a cache compiled from old ones, left there by an earlier build would ship too
        shutil.rmtree(os.path.join(self.build_lib, "c3bf_gym"), ignore_errors=True)
        super().run()
        if getattr(self, "editable_mode", False) or os.environ.get("C3BF_GYM_PRECOMPILE", "1") == "0":
            return
        # the built package first, then this process's own path: pip's build isolation reaches the
        # build requirements through it (a sitecustomize module with older pips)
        paths = [os.path.abspath(self.build_lib), *(p for p in sys.path if p and os.path.isdir(p))]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
        env.pop("NUMBA_CACHE_DIR", None)  # the cache goes beside the built sources
        done = subprocess.run([sys.executable, "-m", "c3bf_gym._precompile"], cwd=self.build_lib, env=env,
                              capture_output=True, text=True)
        print(done.stdout.strip() or done.stderr.strip()[-2000:], file=sys.stderr)


setup(cmdclass={"build_py": BuildWithKernels})
