"""twinbench: evaluate robot manipulation policies in photorealistic digital twins.

Importing twinbench registers its gymnasium env ids (entry points as strings: nothing heavy is
imported until an env is made). An installed twinbench also registers them whenever gymnasium is imported
(the `twinbench-gym.pth` startup hook, see `_twinbench_gym_hook`; off with TWINBENCH_NO_GYM_HOOK=1), so
`gymnasium.make("twinbench/PushT-v0")` works in any interpreter without `import twinbench`.
"""

__version__ = "0.1.0"

# env id -> (entry point, kwargs, max_episode_steps)
ENV_IDS = {
    "twinbench/PushT-v0": ("twinbench.env:TwinEnv", {"task": "push-t"}, None),
    "twinbench/RopeRouting-v0": ("twinbench.env:TwinEnv", {"task": "rope-routing"}, None),
    "twinbench/ToyPacking-v0": ("twinbench.env:TwinEnv", {"task": "toy-packing"}, None),
    "twinbench/PointReach-v0": ("twinbench.tasks.point_reach:PointReachEnv", {}, 60),
}


def register_envs() -> None:
    """Register twinbench's env ids with gymnasium (idempotent)."""
    import gymnasium

    for env_id, (entry_point, kwargs, max_steps) in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            vector = "twinbench.env:TwinVectorEnv" if entry_point == "twinbench.env:TwinEnv" else None
            gymnasium.register(id=env_id, entry_point=entry_point, vector_entry_point=vector,
                               kwargs=dict(kwargs), max_episode_steps=max_steps)


register_envs()
