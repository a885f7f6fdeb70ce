"""Training the neural graph-matching solver (NGM, core/solvers/ngm.py) on problems from the
project's own generators: problems (the training problems in both formulations), net (the
network in torch), train (the seeded training run). torch is needed only here (`train` extra).
"""

from mergesvc.sim.ngm.problems import NGMProblem, problems
from mergesvc.sim.ngm.train import INSTALL_HINT, TrainConfig, TrainResult, require_torch, train

__all__ = ["INSTALL_HINT", "NGMProblem", "TrainConfig", "TrainResult", "problems",
           "require_torch", "train"]
