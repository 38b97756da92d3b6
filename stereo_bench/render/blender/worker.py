"""The process that runs inside the worker environment: Blender (``bpy``) or the 2D pose detector.

Started by :mod:`stereo_bench.render.blender.client` as ``python worker.py render`` or
``python worker.py pose2d`` with the worker environment's interpreter; it imports neither
``stereo_bench`` nor anything of the main environment (its numpy is < 2, bpy's and mediapipe's).

Protocol: one JSON object per line on stdin, one reply per line on a private copy of stdout
(Blender and TensorFlow Lite print to file descriptor 1, which is pointed at stderr). A request is
``{"op": NAME, ...}``; the reply is ``{"ok": true, ...}`` or ``{"ok": false, "error": TEXT}``; the
worker exits at end of input. Images travel as files whose paths the client gives (inside its
output folder); arrays as .npy files.

Cameras are pinhole (the client renders undistorted and applies the lens itself):
``{"width", "height", "fx", "fy", "cx", "cy", "cam_from_world": 4x4 (m), "sensor_mm",
"focal_mm", "f_number", "focus_m"}`` with OpenCV's conventions (x right, y down, z forward,
pixel centres at integers). Blender's camera looks down -Z with +Y up, so its object's world
matrix is inverse(FLIP @ cam_from_world), FLIP = diag(1, -1, -1, 1). The projection matches
OpenCV's exactly with a horizontal sensor fit, lens = fx * sensor / W, pixel aspect y/x = fx/fy
and the shifts below, whose 0.5 terms move Blender's pixel-edge origin to OpenCV's pixel centres.
"""

import json
import os
import sys

FLIP = ((1, 0, 0, 0), (0, -1, 0, 0), (0, 0, -1, 0), (0, 0, 0, 1))


def _matmul(a, b):
    return [[sum(a[i][k] * b[k][j] for k in range(4)) for j in range(4)] for i in range(4)]


# ----------------------------------------------------------------------------------- Blender
class Blender:
    """One Cycles scene, kept between requests: the setup is paid once per scene, a frame only
    moves objects and renders."""

    def __init__(self):
        import bpy  # noqa: PLC0415 (only this process has bpy)

        self.bpy = bpy
        self.objects = {}

    # --- scene --------------------------------------------------------------------------------
    def _reset(self, samples, threads, raw, noise_threshold=0.0):
        bpy = self.bpy
        bpy.ops.wm.read_factory_settings(use_empty=True)
        self.objects = {}
        scene = bpy.context.scene
        scene.render.engine = "CYCLES"
        cycles = scene.cycles
        cycles.device = "CPU"
        cycles.samples = int(samples)
        # Adaptive sampling: a pixel of flat print or background has no variance and stops
        # early; the board's edges, where the pixel's area is split, take every sample.
        cycles.use_adaptive_sampling = noise_threshold > 0
        if noise_threshold > 0:
            cycles.adaptive_threshold = float(noise_threshold)
        cycles.use_denoising = False
        # A box filter one pixel wide: each pixel is the mean over its own area, as a sensor's
        # pixel integrates (Blackman-Harris, the default, reaches into the neighbours).
        cycles.pixel_filter_type = "BOX"
        cycles.filter_width = 1.0
        cycles.seed = 0
        cycles.max_bounces = 2
        scene.render.threads_mode = "FIXED" if threads else "AUTO"
        if threads:
            scene.render.threads = int(threads)
        scene.render.resolution_percentage = 100
        scene.render.dither_intensity = 0.0
        scene.render.film_transparent = False
        # Raw: the film's linear values go to the file unchanged (grey levels of the board);
        # Standard: the sRGB look of a photograph (the body, for a detector trained on photos).
        scene.view_settings.view_transform = "Raw" if raw else "Standard"
        scene.view_settings.look = "None"
        scene.view_settings.exposure = 0.0
        scene.view_settings.gamma = 1.0
        settings = scene.render.image_settings
        settings.file_format = "PNG"
        settings.color_depth = "16" if raw else "8"
        settings.color_mode = "BW" if raw else "RGB"
        settings.compression = 15
        world = bpy.data.worlds.new("world")
        scene.world = world
        return scene

    def _world(self, seen, ambient):
        """Camera rays see the grey ``seen``; everything else is lit by ``ambient``."""
        world = self.bpy.context.scene.world
        world.use_nodes = True
        nt = world.node_tree
        nt.nodes.clear()
        path = nt.nodes.new("ShaderNodeLightPath")
        lit = nt.nodes.new("ShaderNodeBackground")
        lit.inputs["Color"].default_value = (*[ambient] * 3, 1.0)
        shown = nt.nodes.new("ShaderNodeBackground")
        shown.inputs["Color"].default_value = (*seen, 1.0)
        mix = nt.nodes.new("ShaderNodeMixShader")
        out = nt.nodes.new("ShaderNodeOutputWorld")
        nt.links.new(path.outputs["Is Camera Ray"], mix.inputs[0])
        nt.links.new(lit.outputs[0], mix.inputs[1])
        nt.links.new(shown.outputs[0], mix.inputs[2])
        nt.links.new(mix.outputs[0], out.inputs["Surface"])

    def _sun(self, direction_cam, strength):
        """A sun whose light travels along ``direction_cam`` (OpenCV camera frame of camera 0 /
        the world frame given) with irradiance ``strength`` W/m^2."""
        bpy = self.bpy
        light = bpy.data.lights.new("sun", type="SUN")
        light.energy = float(strength)
        light.angle = 0.0
        obj = bpy.data.objects.new("sun", light)
        bpy.context.scene.collection.objects.link(obj)
        d = [float(v) for v in direction_cam]
        n = sum(v * v for v in d) ** 0.5
        z = [-v / n for v in d]  # the sun shines along its local -Z
        helper = [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0]
        x = _cross(helper, z)
        xn = sum(v * v for v in x) ** 0.5
        x = [v / xn for v in x]
        y = _cross(z, x)
        obj.matrix_world = _as_matrix(self.bpy, [[x[0], y[0], z[0], 0], [x[1], y[1], z[1], 0],
                                                 [x[2], y[2], z[2], 0], [0, 0, 0, 1]])

    def _camera(self, name, spec):
        bpy = self.bpy
        data = bpy.data.cameras.new(name)
        obj = bpy.data.objects.new(name, data)
        bpy.context.scene.collection.objects.link(obj)
        W, H = int(spec["width"]), int(spec["height"])
        fx, fy, cx, cy = (float(spec[k]) for k in ("fx", "fy", "cx", "cy"))
        data.sensor_fit = "HORIZONTAL"
        data.sensor_width = float(spec["sensor_mm"])
        data.lens = fx * data.sensor_width / W
        data.shift_x = (W / 2 - 0.5 - cx) / W
        data.shift_y = (cy + 0.5 - H / 2) * (fx / fy) / W
        data.clip_start = 1e-3
        data.clip_end = 1e4
        if spec.get("f_number"):
            data.dof.use_dof = True
            data.dof.aperture_fstop = float(spec["f_number"])
            data.dof.focus_distance = float(spec["focus_m"])
        obj.matrix_world = _as_matrix(bpy, _invert_rigid(_matmul(FLIP, spec["cam_from_world"])))
        self.objects[name] = (obj, spec)
        return obj

    def _use_camera(self, name):
        obj, spec = self.objects[name]
        scene = self.bpy.context.scene
        scene.camera = obj
        scene.render.resolution_x = int(spec["width"])
        scene.render.resolution_y = int(spec["height"])
        ratio = float(spec["fx"]) / float(spec["fy"])
        scene.render.pixel_aspect_x = 1.0 if ratio >= 1 else 1.0 / ratio
        scene.render.pixel_aspect_y = ratio if ratio >= 1 else 1.0

    def _render(self, path):
        scene = self.bpy.context.scene
        scene.render.filepath = path
        self.bpy.ops.render.render(write_still=True)

    def _material(self, name, color_socket_from, emission):
        """A matte material whose colour comes from ``color_socket_from(node_tree)``: emission
        (uniform light, the colour is the film value) or a diffuse BSDF (lit)."""
        bpy = self.bpy
        mat = bpy.data.materials.new(name)
        mat.use_nodes = True
        nt = mat.node_tree
        nt.nodes.clear()
        shader = nt.nodes.new("ShaderNodeEmission" if emission else "ShaderNodeBsdfDiffuse")
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(color_socket_from(nt), shader.inputs["Color"])
        nt.links.new(shader.outputs[0], out.inputs["Surface"])
        return mat

    def _mesh(self, name, vertices, faces, material, uvs=None):
        bpy = self.bpy
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata([tuple(v) for v in vertices], [], [tuple(f) for f in faces])
        if uvs is not None:
            layer = mesh.uv_layers.new(name="uv")
            for loop in mesh.loops:
                layer.data[loop.index].uv = uvs[loop.vertex_index]
        mesh.materials.append(material)
        mesh.update()
        obj = bpy.data.objects.new(name, mesh)
        bpy.context.scene.collection.objects.link(obj)
        return obj

    # --- requests -----------------------------------------------------------------------------
    def board(self, req):
        """Set up a board scene: the textured plane, the camera, the light."""
        self._reset(req["samples"], req.get("threads"), raw=True,
                    noise_threshold=req.get("noise_threshold", 0.0))
        light = req["light"]
        emission = light is None
        self._world([req["background"]] * 3, 0.0 if emission else light["ambient"])
        image = self.bpy.data.images.load(req["texture"])
        image.colorspace_settings.name = "Non-Color"

        def texture(nt):
            node = nt.nodes.new("ShaderNodeTexImage")
            node.image = image
            node.interpolation = "Linear"
            node.extension = "EXTEND"
            return node.outputs["Color"]

        material = self._material("board", texture, emission)
        x0, y0, x1, y1 = (float(v) for v in req["extent_m"])
        corners = [(x0, y0, 0.0), (x1, y0, 0.0), (x1, y1, 0.0), (x0, y1, 0.0)]
        # Blender's image v runs up from the bottom row; the texture's rows run down with y.
        uvs = [(0.0, 1.0), (1.0, 1.0), (1.0, 0.0), (0.0, 0.0)]
        self.board_obj = self._mesh("board", corners, [(0, 1, 2, 3)], material, uvs)
        self._camera("camera", req["camera"])
        self._use_camera("camera")
        if not emission:
            # Diffuse albedo rho under a sun of irradiance E gives radiance rho E cos / pi: E = pi
            # (1 - ambient) makes the print's grey level rho ((1 - ambient) cos + ambient).
            self._sun(light["direction"], 3.141592653589793 * (1.0 - light["ambient"]))
        return {}

    def board_frame(self, req):
        """Render the board at ``cam_from_board`` (4x4, m) into ``out``; with ``region``
        [x0, y0, x1, y1] (pixels, ends exclusive, rows from the top) only those pixels (the
        rest of the file is left at 0: the caller knows what is there)."""
        pose = _matmul(FLIP, req["cam_from_board"])
        cam = self.objects["camera"][0]
        self.board_obj.matrix_world = cam.matrix_world @ _as_matrix(self.bpy, pose)
        render = self.bpy.context.scene.render
        region = req.get("region")
        render.use_border = region is not None
        if region is not None:
            x0, y0, x1, y1 = region
            width, height = render.resolution_x, render.resolution_y
            render.use_crop_to_border = False
            render.border_min_x, render.border_max_x = x0 / width, x1 / width
            # Blender's border rows run up from the bottom of the image.
            render.border_min_y, render.border_max_y = 1 - y1 / height, 1 - y0 / height
        self._render(req["out"])
        return {}

    def body(self, req):
        """Set up a body scene: the mesh (per-vertex colours), a floor, the cameras, a sun."""
        import numpy as np  # noqa: PLC0415 (the worker's own numpy)

        self._reset(req["samples"], req.get("threads"), raw=False)
        self._world(req["background"], req["ambient"])
        faces = np.load(req["faces"])
        colors = np.load(req["colors"])
        vertices = np.load(req["vertices"], mmap_mode="r")
        self.body_vertices = req["vertices"]

        def vertex_color(nt):
            node = nt.nodes.new("ShaderNodeAttribute")
            node.attribute_name = "skin"
            return node.outputs["Color"]

        material = self._material("body", vertex_color, emission=False)
        obj = self._mesh("body", vertices[0], faces, material)
        attr = obj.data.color_attributes.new("skin", "FLOAT_COLOR", "POINT")
        rgba = np.concatenate([colors, np.ones((len(colors), 1))], axis=1).astype(np.float32)
        attr.data.foreach_set("color", rgba.ravel())
        for poly in obj.data.polygons:
            poly.use_smooth = True
        self.body_obj = obj
        floor = req["floor"]

        def checker(nt):
            node = nt.nodes.new("ShaderNodeTexChecker")
            node.inputs["Color1"].default_value = (*floor["colors"][0], 1.0)
            node.inputs["Color2"].default_value = (*floor["colors"][1], 1.0)
            node.inputs["Scale"].default_value = float(floor["squares"])
            coords = nt.nodes.new("ShaderNodeTexCoord")
            nt.links.new(coords.outputs["UV"], node.inputs["Vector"])
            return node.outputs["Color"]

        self._mesh("floor", floor["corners"], [(0, 1, 2, 3)], self._material("floor", checker,
                                                                                False),
                   [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)])
        for name, spec in req["cameras"].items():
            self._camera(name, spec)
        self._sun(req["sun_direction"], req["sun_strength"])
        return {}

    def body_frame(self, req):
        """Pose the mesh at frame ``frame`` of the vertices file and render every camera into
        ``out[name]``."""
        import numpy as np  # noqa: PLC0415

        vertices = np.load(self.body_vertices, mmap_mode="r")[int(req["frame"])]
        mesh = self.body_obj.data
        mesh.vertices.foreach_set("co", np.ascontiguousarray(vertices, np.float32).ravel())
        mesh.update()
        for name, path in req["out"].items():
            self._use_camera(name)
            self._render(path)
        return {}


def _cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _invert_rigid(m):
    R = [[m[j][i] for j in range(3)] for i in range(3)]
    t = [-sum(R[i][k] * m[k][3] for k in range(3)) for i in range(3)]
    return [R[0] + [t[0]], R[1] + [t[1]], R[2] + [t[2]], [0, 0, 0, 1]]


def _as_matrix(bpy, rows):
    from mathutils import Matrix  # noqa: PLC0415 (ships with bpy)

    return Matrix([[float(v) for v in row] for row in rows])


# ----------------------------------------------------------------------------------- pose 2D
class Pose2D:
    """MediaPipe's BlazePose GHUM "full" model (the weights inside mediapipe's wheel; complexity
    0 and 2 would download theirs), one image at a time, static mode (no tracking: each frame
    is detected alone, as each camera's view is)."""

    def __init__(self):
        import mediapipe as mp  # noqa: PLC0415 (only this environment has it)

        self.pose = mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1,
                                           enable_segmentation=False,
                                           min_detection_confidence=0.3)

    def landmarks(self, req):
        """Landmarks of every image in ``images`` into ``out`` (.npy, (N, 33, 4): x, y in px
        with the image's left/top edge at 0, visibility, presence; NaN where no body)."""
        import cv2  # noqa: PLC0415 (mediapipe's OpenCV)
        import numpy as np  # noqa: PLC0415

        result = np.full((len(req["images"]), 33, 4), np.nan)
        for i, path in enumerate(req["images"]):
            bgr = cv2.imread(path, cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"{path}: not a readable image")
            found = self.pose.process(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).pose_landmarks
            if found is None:
                continue
            h, w = bgr.shape[:2]
            result[i] = [(p.x * w, p.y * h, p.visibility, p.presence) for p in found.landmark]
        np.save(req["out"], result)
        return {"found": int(np.isfinite(result[:, 0, 0]).sum())}


def main():
    mode = sys.argv[1] if len(sys.argv) > 1 else ""
    replies = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # what the libraries print goes to stderr, never into the replies
    try:
        handler = {"render": Blender, "pose2d": Pose2D}[mode]()
    except KeyError:
        replies.write(json.dumps({"ok": False, "error": f"unknown mode {mode!r}"}) + "\n")
        return 2
    except Exception as e:  # the client names what failed to import
        replies.write(json.dumps({"ok": False, "error": f"{type(e).__name__}: {e}"}) + "\n")
        return 1
    replies.write(json.dumps({"ok": True, "ready": mode}) + "\n")
    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            req = json.loads(line)
            op = getattr(handler, req["op"], None)
            if op is None or req["op"].startswith("_"):
                raise ValueError(f"unknown op {req['op']!r}")
            reply = {"ok": True, **op(req)}
        except Exception as e:  # one failed request is reported; the worker serves the next
            reply = {"ok": False, "error": f"{type(e).__name__}: {e}"}
        replies.write(json.dumps(reply) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
