"""A policy for the websocket tests to serve: doubles `agent_pos`; raises on the prompt "crash"."""

import numpy as np


class Doubler:
    def reset(self):
        pass

    def select_action(self, obs):
        if obs.get("prompt") == "crash":
            raise ValueError("bad observation")
        return 2 * np.asarray(obs["agent_pos"], np.float32)
