"""What the PyBullet engine's rollouts cost against a bare PyBullet stepping loop, in the same run.

Both roll the real cube's val tosses out from the protocol's context with PyBullet's default parameters. The bare
loop is the least a Python caller can do: one world, reset the body, step, read pose and velocity each frame. The
engine adds the mesh/inertial frame conversion, the manifold reset between tosses and the stability judgement, and
spreads tosses over worker processes. Prints seconds and the ratios. python benchmarks/bullet_rollout.py [--repeats 3]
"""

from __future__ import annotations

import argparse

import pybullet
from metrics_speed import best_time  # a sibling script: python benchmarks/... puts benchmarks/ on the path

from contactbench import rotations
from contactbench.config import REPO_ROOT
from contactbench.protocol import make_context
from contactbench.recordings import read_recordings
from contactbench.sim.bullet_engine import BulletEngine
from contactbench.sim.rollout import available_cores


def bare_loop(scene, context) -> None:
    """PyBullet alone: a plane and the cube's convex hull, every toss stepped and read frame by frame."""
    client = pybullet.connect(pybullet.DIRECT)
    try:
        pybullet.setPhysicsEngineParameter(fixedTimeStep=scene.dt, numSubSteps=0, physicsClientId=client)
        pybullet.setGravity(*scene.gravity.tolist(), physicsClientId=client)
        plane = pybullet.createCollisionShape(pybullet.GEOM_PLANE, physicsClientId=client)
        pybullet.createMultiBody(0.0, plane, physicsClientId=client)
        shape = pybullet.createCollisionShape(
            pybullet.GEOM_MESH, vertices=scene.body_mesh(0).vertices.tolist(), physicsClientId=client
        )
        body = pybullet.createMultiBody(scene.bodies[0].mass, shape, physicsClientId=client)
        for pose, velocity, length in zip(context.poses[:, -1, 0], context.velocities[:, -1, 0], context.lengths):
            pybullet.resetBasePositionAndOrientation(
                body, pose[:3].tolist(), rotations.wxyz_to_xyzw(pose[3:]).tolist(), physicsClientId=client
            )
            pybullet.resetBaseVelocity(body, velocity[:3].tolist(), velocity[3:].tolist(), physicsClientId=client)
            states = []
            for _ in range(int(length) - context.n_context):
                pybullet.stepSimulation(physicsClientId=client)
                states.append(pybullet.getBasePositionAndOrientation(body, physicsClientId=client))
                states.append(pybullet.getBaseVelocity(body, physicsClientId=client))
    finally:
        pybullet.disconnect(physicsClientId=client)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    dataset = read_recordings(REPO_ROOT / "assets" / "contactnets_cube", ["val"])
    context = make_context(dataset.split("val"), dataset.dt, 6)
    scene = dataset.for_models()
    engine = BulletEngine()
    parameters = engine.default_parameters(scene.n_bodies)
    bare = best_time(lambda: bare_loop(scene, context), args.repeats)
    one = engine.rollouts(scene, nthread=1)
    wrapped = best_time(lambda: one.rollout_context(context, parameters), args.repeats)
    cores = available_cores()
    spread = engine.rollouts(scene, nthread=cores)
    spread.rollout_context(context, parameters)  # the workers start once per search, not per call
    parallel = best_time(lambda: spread.rollout_context(context, parameters), args.repeats)
    spread.close()
    frames = int((context.lengths - context.n_context).sum())
    print(f"real cube val: {len(context.lengths)} tosses, {frames} predicted frames; best of {args.repeats}")
    print(f"bare PyBullet loop, one process:     {bare:.3f} s  ({1e3 * bare / len(context.lengths):.2f} ms per toss)")
    print(f"engine rollouts, one process:        {wrapped:.3f} s  ratio {wrapped / bare:.2f}x the bare loop")
    print(f"engine rollouts, {cores} worker processes: {parallel:.3f} s  ratio {parallel / bare:.2f}x the bare loop")


if __name__ == "__main__":
    main()
