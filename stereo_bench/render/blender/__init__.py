"""The photoreal backend: Blender's Cycles in a worker process of its own environment.

The core never imports bpy: :mod:`.environment` builds and finds the worker environment,
:mod:`.client` talks to :mod:`.worker` (which runs there), :mod:`.lens` renders undistorted and
applies the camera's lens exactly, :mod:`.board` renders boards behind the analytic renderer's
interface.
"""
