"""The one list of sensor renderer names (no imports, so launch tools can read it cheaply).

'fast': OpenGL rasterization (moderngl, headless EGL) and Embree ray casting
(cps_sim.fast_sensors); 'egl', 'tiny': PyBullet's EGL plugin or TinyRenderer with its
rayTestBatch; 'auto': the cheaper of PyBullet's two for the frame size.
"""

RENDERERS = ("fast", "egl", "tiny", "auto")
DEFAULT_RENDERER = "fast"
