# %% [markdown]
# # Tutorial: from a space to a confirmed body, on a CPU
#
# A plain Python script in sections (jupytext's percent format, so it also opens as a
# notebook). It makes a space, looks at bodies, evaluates a batch, runs a short search on the
# table fitness, confirms the best body with freshly trained controllers, films it and reads
# the run's body log:
#
# ```bash
# pip install -e . && python examples/tutorial.py          # writes into tutorial_out/
# ```
#
# On a 2-core CPU it took 2 min 24 s, most of it compiling; `python
# examples/tutorial.py DIR` writes into DIR instead (the test `tests/test_tutorial.py` runs
# it so).

# %%
import json
import shutil
import sqlite3
import sys
import time
from pathlib import Path

import jax
import matplotlib.pyplot as plt

import evojax_morph as em
from evojax_morph import tasks
from evojax_morph.figures import plots, video
from evojax_morph.records.bodylog import shapes
from evojax_morph.records.saved_controllers import SavedController
from evojax_morph.run import cli

OUT = Path(sys.argv[1] if len(sys.argv) > 1 else "tutorial_out")
OUT.mkdir(parents=True, exist_ok=True)
start = time.perf_counter()

# %% [markdown]
# ## 1. A space and its bodies
#
# A space names its bodies' parts and mutations. Bad Walker is a planar trunk with a long
# foot in its middle and two short feet; a mutation moves a foot to one of 4 trunk
# locations or removes it. Its first body, m0, balances on the long foot.

# %%
space = em.make_space("bad_walker")
m0 = space.initial()
print(space.format(m0))
print("mutations:", space.mutation_names)
mask = space.action_mask(m0)  # bool (max_nodes, num_mutations): which mutations are allowed
print("allowed mutations of m0:", int(mask.sum()), "of", mask.size)

# %% [markdown]
# A body is a padded tree of arrays (`em.Morphology`); a mutation `(node, mutation)` is a pure
# function of it. Removing the long foot (node 1, `remove`), then moving the short feet
# (nodes 2 and 3) to the ends of the trunk gives m*, the optimum of the space's hand-made
# ("predefined") fitness. `space.canonical` names a body by its shape.

# %%
m_star = space.mutate(m0, 1, 4)  # remove the long foot
m_star = space.mutate(m_star, 2, 0)  # back foot to the back end
m_star = space.mutate(m_star, 3, 3)  # front foot to the front end
print(space.format(m_star))
print(space.canonical(m_star))
print("predefined fitness: m0", round(float(space.predefined_fitness(m0)), 3),
      "m*", round(float(space.predefined_fitness(m_star)), 3))

# %% [markdown]
# Draw bodies with matplotlib, or export one as MJCF for MuJoCo's own viewer
# (`python -m mujoco.viewer --mjcf=tutorial_out/m0.xml`):

# %%
keys = jax.random.split(jax.random.PRNGKey(0), 8)
morphs = jax.vmap(space.random_morphology, (0, None))(keys, 3)  # 8 bodies, 3 mutations each
fig, axes = plt.subplots(1, 4, figsize=(10, 1.6))
for ax, i in zip(axes, range(4)):
    body = jax.tree.map(lambda x, i=i: x[i], morphs)
    plots.draw_morphology(ax, space, body)
    ax.set_title(f"body {i}", fontsize=8)
fig.savefig(OUT / "bodies.png", dpi=80)
plt.close(fig)
(OUT / "m0.xml").write_text(space.to_mjcf(m0))

# %% [markdown]
# ## 2. Evaluate a batch
#
# `em.evaluate` scores a whole batch of bodies in one compiled call. The predefined fitness
# is a formula; the PPO fitness trains a controller on every body (here 20,000 PPO steps, a
# minute or two on a CPU, most of it compiling; a GPU run trains 50,000 to 100,000) and
# reports its return, the metres it moved forward in the 5 s episode and the fraction of the
# episode it stayed upright.

# %%
result = em.evaluate(space, morphs, jax.random.PRNGKey(1), em.FitnessConfig(kind="predefined"))
print("predefined:", result.fitness)

ppo = em.FitnessConfig(kind="ppo", task=em.make_task("walk"), ppo=em.standard_ppo(20_000))
four = jax.tree.map(lambda x: x[:4], morphs)
result = em.evaluate(space, four, jax.random.PRNGKey(2), ppo)
print("PPO fitness:", result.fitness)
print("metres forward:", result.distance, "fraction upright:", result.upright)

# %% [markdown]
# ## 3. A short search on the table fitness
#
# The table fitness looks each body up in a landscape table of PPO results (every Bad Walker
# body x 32 controllers of 50,000 steps on the walking task, built on a GPU) and returns the
# mean of `--controllers` of them, so a search costs seconds, not GPU hours. The run command
# does it (`run.main` takes its flags from Python): 8 parallel evolutions of Double-DQN for 20
# steps, then the bodies of the highest mean in its body log confirmed with 16 fresh draws
# each.

# %%
run_dir = OUT / "run"
shutil.rmtree(run_dir, ignore_errors=True)  # a second run of the tutorial starts afresh
table = Path(__file__).resolve().parent.parent / "docs/landscapes/bad_walker_walk.npz"
flags = ["--space", "bad_walker", "--fitness", "table", "--table", str(table),
         "--controllers", "4", "--num-envs", "8", "--steps", "20", "--explore-steps", "10",
         "--confirm", "4", "--confirm-controllers", "16", "--out", str(run_dir)]
assert cli.main(flags) == 0
summary = json.loads((run_dir / "summary.json").read_text())
for c in summary["confirmed"]:
    print(f"{c['body']}: {c['mean']:.1f} [{c['ci95'][0]:.1f}, {c['ci95'][1]:.1f}]")

# %% [markdown]
# ## 4. The body log
#
# Every evaluation of the run is a row of `bodies.sqlite`; `em.best_bodies` ranks the
# distinct bodies by their mean fitness, and any SQL asks the rest.

# %%
log = run_dir / "bodies.sqlite"
for row in em.best_bodies(log, 5):
    print(row["body"], row["evaluations"], round(row["mean_fitness"], 1))
db = sqlite3.connect(log)
print(db.execute("SELECT COUNT(*), COUNT(DISTINCT body) FROM bodies").fetchone())
db.close()

# %% [markdown]
# ## 5. Confirm the best body with trained controllers, and film it
#
# The table holds results, not controllers, so to watch the confirmed best body we train
# controllers on it afresh: `em.confirm` evaluates it C = 4 times, each time with a new
# controller, and keeps them. A body *walks* when it is confirmed at a mean of at least 2 m
# in the 5 s episode and upright the whole episode in at least 90% of its confirming
# evaluations, and *moves* otherwise (`tasks.gait_word`); at 20,000 PPO steps expect one
# that moves. `video.render_saved` replays the best of the 4 controllers and writes a GIF,
# drawn by MuJoCo's renderer where OpenGL works, else by matplotlib.

# %%
best_name = summary["confirmed"][0]["body"]
best = shapes(log, space, [best_name])[best_name]
[confirmed] = em.confirm(space, em.stack([best]), jax.random.PRNGKey(3), ppo, controllers=4)
print(f"{best_name}: fitness {confirmed.mean:.1f}, {confirmed.distance.mean():.2f} m, "
      f"upright the whole episode in {confirmed.upright_whole:.0%}:",
      tasks.gait_word(confirmed.distance.mean(), confirmed.upright_whole))

k = int(confirmed.values.argmax())
saved = SavedController(space, ppo.with_controllers(1), seed=3, morph=confirmed.morph,
                        params=jax.tree.map(lambda x: x[k], confirmed.params),
                        value=float(confirmed.values[k]), label="best")
rendered = video.render_saved(saved, OUT / "best", mp4=False)
print("wrote", [str(p) for p in rendered.paths], "drawn by", rendered.backend)
print(f"done in {time.perf_counter() - start:.0f} s")
