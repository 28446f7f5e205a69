"""Build hook: ship the gymnasium registration hook (src/twinbench-gym.pth + src/_twinbench_gym_hook.py) in
regular wheels and editable installs alike (see src/_twinbench_gym_hook.py)."""

from hatchling.builders.hooks.plugin.interface import BuildHookInterface


class GymHook(BuildHookInterface):
    def initialize(self, version, build_data):
        if version == "editable":  # src/ is on sys.path through hatchling's own .pth, which loads first
            build_data["force_include_editable"]["src/twinbench-gym.pth"] = "twinbench-gym.pth"
        else:
            build_data["force_include"]["src/twinbench-gym.pth"] = "twinbench-gym.pth"
            build_data["force_include"]["src/_twinbench_gym_hook.py"] = "_twinbench_gym_hook.py"
