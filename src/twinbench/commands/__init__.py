"""One module per `twinbench <command>`: the only place with CLI configs (tyro dataclasses) and `main`s.

A command module parses nothing itself: `twinbench.cli` builds its config with tyro and calls its `main`,
which calls the library (physics ... evaluation, study) and prints. Library modules never import this
package.
"""
