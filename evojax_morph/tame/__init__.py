"""TAME: a task-agnostic fitness from random action primitives (Hejna, Abbeel and Pinto, 2021).

A body is fit when it can *cause* many different outcomes: drive each motor with one of K
random periodic primitives, let the body move, and see whether a classifier can tell from the
final state which primitive drove each motor. With A the primitives (one per motor) and S_T the
final state, TAME ranks bodies by the mutual information I(A; S_T | m), bounded below through a
classifier q(a | s_T, m) (Barber and Agakov):

    I(A; S_T | m) >= H(A) + E[log q(A | s_T, m)] = sum_j (log K + E[log q(a_j | s_T, m)])

for a classifier that factorises over the J motors. We add TAME's state-coverage term, the
entropy of where the body ends up, as a Gaussian estimate over the trunk's final displacement
measured against the state noise sigma (0 for a body that stays put):

    F(m) = sum_j (log K + E[log q(a_j | s_T, m)])
           + coverage * 1/2 log det(I + Cov[dx, dz] / sigma^2)

The reference implementation (github.com/jhejna/morphology-opt) averages the log-likelihood over
motors and multiplies by (log J)^0.25, and gets coverage only implicitly, from noise added to
the final states while training; the sum is the bound itself and needs no such regulariser.

Primitives (TAME's cosine policy): motor j gets u_j(t) = cos(2 pi f t / period + phi), with f in
{1, 2, ...} (`num_freqs`) and phi in {0, 2 pi / num_phases, ...}: K = num_freqs x num_phases.
An episode is `episode_length` control steps of the locomotion task's physics (50 Hz, reset
noise on), with no reward and no termination. The final state of a node is its body's
displacement (dx, dz) since reset and its orientation (cos, sin of the pitch); a welded limb
(a Constructor edge) reads its slot's body, which rides on the trunk.

The classifier is a `gnn.TreeGNN` over the morphology tree (so it can score bodies it never
saw), fed each node's morphology features and final state, with one logit per primitive and
node. It is trained by TAME's own loop (`pretrain`): a population grows a genealogy of bodies,
each body's rollouts go into a buffer, the classifier trains on the buffer each generation,
and the fittest bodies are mutated. The source scored the classifier only on bodies it had
trained on; `pretrain` keeps a set of held-out bodies out of the genealogy and reports the
classifier's accuracy and log-likelihood on them every generation.

The package, by job: `classifier` (q), `fitness` (rollouts and F), `pretraining` (the loop and the
saved classifier); `python -m evojax_morph.tame` (`__main__`) trains and saves one, and the
"tame" fitness kind (`evojax_morph.fitnesses.tame`) loads it.
"""

from evojax_morph.tame.classifier import STATE_SIZE, Classifier, log_likelihood, node_log_likelihood
from evojax_morph.tame.fitness import (
    CPU_MAX_WORLDS,
    Rollouts,
    Tame,
    TameConfig,
    fitness_from,
    fitness_terms,
    init_classifier,
    make_classifier,
    over_bodies,
)
from evojax_morph.tame.pretraining import Pretrained, pick_held_out, pretrain

__all__ = [
    "CPU_MAX_WORLDS",
    "STATE_SIZE",
    "Classifier",
    "Pretrained",
    "Rollouts",
    "Tame",
    "TameConfig",
    "fitness_from",
    "fitness_terms",
    "init_classifier",
    "log_likelihood",
    "make_classifier",
    "node_log_likelihood",
    "over_bodies",
    "pick_held_out",
    "pretrain",
]
