"""Size of the shipped stand-in body model and the speed of its forward pass.

Times 1,000 poses of the walk_circle motion through smplx (batched by pose_eval.body.forward
in chunks of body.CHUNK, CPU, float64 and float32) and through the numpy forward kinematics
that gives the joints alone. Prints figures; passes or fails nothing.

    python benchmarks/body_forward.py [--threads N]   (default: all cores)
"""

import argparse
import os
import time

import torch

from pose_eval import body
from pose_eval.motion import STANDIN_MODEL_PATH, forward_kinematics, make_motion, standin_skeleton

POSES = 1000


def best_time(fn, repeats: int = 3) -> float:
    fn()  # warm-up: first calls allocate and pick kernels
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=os.cpu_count())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    size = STANDIN_MODEL_PATH.stat().st_size
    motion = make_motion("walk_circle", POSES)
    print(f"model file: {STANDIN_MODEL_PATH.name}, {size / 1024:.0f} KiB")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, chunks of {body.CHUNK} poses")
    for dtype in (torch.float64, torch.float32):
        model = body.load_body_model(dtype=dtype)
        seconds = best_time(lambda: body.forward(model, motion.body_pose, motion.global_orient, motion.transl))
        print(f"smplx forward, {POSES} poses, {model.get_num_verts()} vertices, {str(dtype)[6:]}: "
              f"{seconds:.3f} s ({1e3 * seconds / POSES:.2f} ms/pose)")
    skeleton = standin_skeleton()
    seconds = best_time(lambda: forward_kinematics(motion.poses, skeleton, motion.transl))
    print(f"numpy forward kinematics (joints only), {POSES} poses: {seconds * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
