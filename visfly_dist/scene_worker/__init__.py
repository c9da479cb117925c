"""The scene worker: scenes, renderers and obstacle queries served over Zenoh.

Importing this package sets ``PYOPENGL_PLATFORM=egl`` unless already set: headless pyrender needs it
before PyOpenGL is first imported, and every renderer module lives below this package.
"""

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
