"""The C firmware (firmware_c/) from Python through ctypes: the controller core
(``cimpl``) and the agent runtime (``cagent``), built on first use."""
