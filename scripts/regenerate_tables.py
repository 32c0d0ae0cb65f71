#!/usr/bin/env python
"""Write every table in docs/ from the committed results, with the code that writes them in a run.

    python scripts/regenerate_tables.py                       # rewrite the tables in docs/ (and the training curves)
    python scripts/regenerate_tables.py --from-run results    # first copy a main job's results into docs/results/
    python scripts/regenerate_tables.py --out /tmp/tables     # write elsewhere (docs/ is only read)

* ``results/experiments_ur5e/experiments_table.md`` and ``sensing_table.md``: from ``table.json``
  and ``sensing.json`` beside them, copies of what ``c3bf-gym experiments`` (the main job, default
  options; its ``config.json`` beside them) wrote, through
  :func:`c3bf_gym.experiments.markdown_table`: the run's own ``table.md`` and ``sensing.md``.
  ``results/experiments_panda/`` likewise (the main job with ``--robot panda``). Each folder also
  holds the run's figures that the results pages show.
* ``results/training/training_table*.md``: what ``c3bf-gym plot-training docs/runs/GLOB
  --evaluation FILE --out docs/results/training/FIGURE --table docs/results/training/TABLE``
  writes, for each row of :data:`TRAINING_TABLES`, with the table's curves
  (``training_curves*.png``) beside it.

``tests/test_tables.py`` checks that the committed tables equal what this script writes.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DOCS = REPO / "docs"

#: The files of a ``c3bf-gym experiments`` run that each of :data:`EXPERIMENT_FOLDERS` keeps.
RESULT_FILES = ("table.json", "sensing.json", "config.json")
#: Where each robot's experiments live under docs/ (its ``config.json`` names the robot): the run's
#: :data:`RESULT_FILES`, the tables written from them and the figures the results pages show.
EXPERIMENT_FOLDERS = {"ur5e": "results/experiments_ur5e", "panda": "results/experiments_panda"}

#: Where the training tables and their curves live, under docs/ (the RL results page includes them).
TRAINING_FOLDER = "results/training"
#: Training tables: ``(table, run directories under docs/runs (glob), evaluation file, figure)``,
#: the table and the figure in :data:`TRAINING_FOLDER`.
TRAINING_TABLES = (
    ("training_table.md", "sac_residual_10hz_dw10_aw3_set_*", "eval_200.json", "training_curves.png"),
    ("training_table_aw10.md", "sac_residual_10hz_dw10_aw10_set_*", "eval_200.json", "training_curves_aw10.png"),
    ("training_table_aw1_set.md", "sac_residual_10hz_dw10_aw1_set_*", "final_eval.json", "training_curves_aw1_set.png"),
    ("training_table_aw1.md", "sac_residual_10hz_dw10_aw1_[!s]*", "final_eval.json", "training_curves_aw1.png"),
    # the default filter's recipe re-run on the DAQP core (code 0293869)
    ("training_table_daqp.md", "daqp_core/sac_residual_10hz_dw10_aw3_set_*", "eval_200.json", "training_curves_daqp.png"),
    # the same on the final core (code be667d7)
    ("training_table_final.md", "final_core/sac_residual_10hz_dw10_aw3_set_*", "eval_200.json", "training_curves_final.png"),
    # the Panda: no filter and the default filter, the same recipe (code be667d7)
    ("training_table_panda.md", "panda/panda_sac_residual_10hz_dw10_aw3_set_*", "eval_200.json", "training_curves_panda.png"),
    # RLlib PPO, the default filter, 2 env runners (code 9f6e3ed)
    ("training_table_rllib_ppo.md", "rllib_ppo/rllib_ppo_residual_10hz_dw10_aw3_*", "eval_200.json", "training_curves_rllib_ppo.png"),
    # SB3 PPO, 2 SubprocVecEnv envs: no filter, HOCBF and the default filter (code 1e683fb)
    ("training_table_ppo.md", "ppo/ppo_residual_10hz_dw10_aw3_set_*", "eval_200.json", "training_curves_ppo.png"),
    # the default filter's SAC recipe trained twice as long, 50k steps (code b762c7e)
    ("training_table_sac_50k.md", "sac_50k/sac_residual_10hz_dw10_aw3_set_*", "eval_200.json", "training_curves_sac_50k.png"),
    # the sets of the README's RL table: the Panda with its 2 N m/rad posture pull, no filter and the
    # default filter, each run's own evaluation on 200 episodes (code 51994f2)
    ("training_table_sets_panda.md", "sets/panda_sac_residual_10hz_dw10_aw3_set_*_random_s*", "final_eval.json",
     "training_curves_sets_panda.png"),
    ("training_table_sets_ur5e.md", "sets/sac_residual_10hz_dw10_aw3_set_*", "final_eval.json",
     "training_curves_sets_ur5e.png"),
    # measured, not adopted: the default filter with the barrier's rows ranked by their allowance (code b921cc4),
    # both arms' sets, and the Panda's trained for 50k steps on it
    ("training_table_sets_panda_allowance.md", "sets_allowance/panda_sac_residual_10hz_dw10_aw3_set_*",
     "final_eval.json", "training_curves_sets_panda_allowance.png"),
    ("training_table_sets_ur5e_allowance.md", "sets_allowance/sac_residual_10hz_dw10_aw3_set_*", "final_eval.json",
     "training_curves_sets_ur5e_allowance.png"),
    ("training_table_sets_panda_allowance_50k.md", "sets_allowance_50k/panda_sac_residual_10hz_dw10_aw3_set_*",
     "final_eval.json", "training_curves_sets_panda_allowance_50k.png"),
    # PPO on the standing filter at its own budget (100k steps), both arms, no filter and the default filter
    # (code 08985b1): SB3 (one env per run, two runs at a time) and RLlib (2 env runners, one run at a time)
    ("training_table_sets_ppo_ur5e.md", "sets_ppo/ppo_residual_10hz_dw10_aw3_set_*", "final_eval.json",
     "training_curves_sets_ppo_ur5e.png"),
    ("training_table_sets_ppo_panda.md", "sets_ppo/panda_ppo_residual_10hz_dw10_aw3_set_*", "final_eval.json",
     "training_curves_sets_ppo_panda.png"),
    ("training_table_sets_rllib_ur5e.md", "sets_rllib/rllib_ppo_residual_10hz_dw10_aw3_*", "final_eval.json",
     "training_curves_sets_rllib_ur5e.png"),
    ("training_table_sets_rllib_panda.md", "sets_rllib/rllib_panda_ppo_residual_10hz_dw10_aw3_*", "final_eval.json",
     "training_curves_sets_rllib_panda.png"),
    # an attempt on the Panda: a dearer correction (--action-weight 10), 5 seeds and one unfiltered run
    ("training_table_sets_panda_aw10.md", "sets/panda_sac_residual_10hz_dw10_aw10_set_*", "final_eval.json",
     "training_curves_sets_panda_aw10.png"),
    # an attempt on the Panda: training on random_multi (multi in half the episodes), evaluated on random
    ("training_table_sets_panda_random_multi.md", "sets/panda_sac_residual_10hz_dw10_aw3_set_c3bf+hocbf_random_multi_*",
     "final_eval.json", "training_curves_sets_panda_random_multi.png"),
    # an attempt on the Panda: quieter exploration (SAC's target entropy -6 instead of -3), 2 seeds
    ("training_table_sets_panda_entropy.md", "sets_entropy/panda_sac_*", "final_eval.json",
     "training_curves_sets_panda_entropy.png"),
    # an attempt on the Panda: the filter's last correction in the observation (--observe-correction), 2 seeds
    ("training_table_sets_panda_oc.md", "sets_oc/panda_sac_*", "final_eval.json",
     "training_curves_sets_panda_oc.png"),
    # an attempt on the UR5e: the Panda's softer posture pull (--posture-stiffness 2), its two weakest seeds
    ("training_table_sets_ur5e_ps2.md", "sets_ps/sac_*", "final_eval.json", "training_curves_sets_ur5e_ps2.png"),
    # the SAC sets of the README's table: the residual action's fade (--residual-fade 0.1, the default since),
    # the default filter on seeds 0-4 and no filter on seeds 0 and 1, both arms (code 045e7f0)
    ("training_table_sets_fade_ur5e.md", "sets_fade/sac_*", "final_eval.json", "training_curves_sets_fade_ur5e.png"),
    ("training_table_sets_fade_panda.md", "sets_fade/panda_sac_residual_10hz_dw10_aw3_*", "final_eval.json",
     "training_curves_sets_fade_panda.png"),
    # the Panda's SAC sets of the README's table: its dearer correction (action weight 10, ACTION_WEIGHTS) with
    # the fade, the default filter on seeds 0-4 (code 045e7f0) and no filter on seeds 0 and 1 (code dad7383)
    ("training_table_sets_fade_panda_aw10.md", "sets_fade/panda_sac_residual_10hz_dw10_aw10_*", "final_eval.json",
     "training_curves_sets_fade_panda_aw10.png"),
    # an attempt on the UR5e: the Panda's dearer correction, stopped after 2 seeds (code dad7383)
    ("training_table_sets_fade_ur5e_aw10.md", "sets_fade_ur5e_aw10/sac_*", "final_eval.json",
     "training_curves_sets_fade_ur5e_aw10.png"),
    # SB3 PPO on today's recipe (the fade; the Panda's action weight 10), the default filter on seeds 0-4 and
    # no filter on seeds 0 and 1, both arms (code 3c4666a)
    ("training_table_sets_ppo_fade_ur5e.md", "sets_ppo_fade/ppo_*", "final_eval.json",
     "training_curves_sets_ppo_fade_ur5e.png"),
    ("training_table_sets_ppo_fade_panda.md", "sets_ppo_fade/panda_ppo_*", "final_eval.json",
     "training_curves_sets_ppo_fade_panda.png"),
    # RLlib PPO on today's recipe (the fade), the UR5e's default filter on seeds 0-4, 2 env runners, one run at a
    # time (code c96e7f6, the filter unchanged since a082084), and no filter on seeds 0 and 1 (code 5c384a8)
    ("training_table_sets_rllib_fade_ur5e.md", "sets_rllib_fade/rllib_ppo_residual_10hz_dw10_aw3_fade0.1_*",
     "final_eval.json", "training_curves_sets_rllib_fade_ur5e.png"),
    # the Panda's RLlib sets on today's recipe (the fade, action weight 10): no filter on seeds 0 and 1 (code
    # 09d39d8), the default filter on seeds 0-4 (code 441059c)
    ("training_table_sets_rllib_fade_panda.md", "sets_rllib_fade/rllib_panda_ppo_*", "final_eval.json",
     "training_curves_sets_rllib_fade_panda.png"),
    # the Panda's SAC sets on the candidate filter: the default's rows with joint_range_reserve=0.3 and
    # allowance_level=True (code 431540c with docs/runs/sets_candidate/variant.patch), seeds 0-4
    ("training_table_sets_candidate_panda.md", "sets_candidate/panda_sac_*", "final_eval.json",
     "training_curves_sets_candidate_panda.png"),
    # the Panda's SAC sets on the allowance level alone: c3bf-gym train --filter-set allowance_level=true
    # (code 930948d), seeds 0-4
    ("training_table_sets_allowance_level_panda.md", "sets_allowance_level/panda_sac_*", "final_eval.json",
     "training_curves_sets_allowance_level_panda.png"),
    # an attempt on the UR5e: training on random_multi (multi in half the episodes), evaluated on random, the
    # default filter, seeds 0 and 1 (code 441059c)
    ("training_table_sets_ur5e_random_multi.md", "sets_ur5e_random_multi/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_random_multi.png"),
    # an attempt on the Panda: the candidate with the speed split (joint_range_reserve=0.3,
    # allowance_level=true, joint_speed_fraction=1.0, nominal_speed_fraction=0.5; code 815766a), seeds 0 and 1
    ("training_table_sets_candidate_speed_panda.md", "sets_candidate_speed/panda_sac_*", "final_eval.json",
     "training_curves_sets_candidate_speed_panda.png"),
    # an attempt on the UR5e: the posture target in the action, c3bf-gym train --posture-reach 0.5
    # --action-weight 9 (code 959cfa9), seeds 0 and 1
    ("training_table_sets_ur5e_posture_reach.md", "sets_posture_reach/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_posture_reach.png"),
    # an attempt on the UR5e: the filter's correction charged in the reward, c3bf-gym train
    # --correction-weight 5 (code 4307e73), seeds 0 and 1
    ("training_table_sets_ur5e_correction_weight.md", "sets_correction_weight/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_correction_weight.png"),
    # an attempt on the UR5e: each arm geom's clearance in the observation, c3bf-gym train --observe-clearance
    # (code bfb8572), seeds 0 and 1
    ("training_table_sets_ur5e_clearance.md", "sets_clearance/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_clearance.png"),
    # an attempt on the UR5e: the residual's straight step bent round the sensed spheres, c3bf-gym train
    # --modulate (code c1ba180), seeds 0 and 1
    ("training_table_sets_ur5e_modulation.md", "sets_modulation/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_modulation.png"),
    # an attempt on the UR5e: the replay buffer stores the action the filter applied, c3bf-gym train
    # --applied-action (Cheng et al. 2019; code 5e8d6dd), seeds 0 and 1
    ("training_table_sets_ur5e_applied_action.md", "sets_applied_action/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_applied_action.png"),
    # an attempt on the UR5e: twice the training with the fade, c3bf-gym train --timesteps 50000, the default
    # filter on seeds 0-4 and no filter on seeds 0 and 1 (code c1ba180, the recipe's own episodes)
    ("training_table_sets_fade_50k_ur5e.md", "sets_fade_50k/sac_*", "final_eval.json",
     "training_curves_sets_fade_50k_ur5e.png"),
    # an attempt on the UR5e: the Cartesian action's reach 0.15 m instead of 0.1, c3bf-gym train
    # --action-reach 0.15 (code 87409e2), seeds 0 and 1
    ("training_table_sets_ur5e_action_reach.md", "sets_action_reach/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_action_reach.png"),
    # an attempt on the UR5e: the share of the episode's time in the observation, and SAC's replay buffer ending
    # each episode at its limit, c3bf-gym train --observe-time (code fb51199), seeds 0 and 1
    ("training_table_sets_ur5e_observe_time.md", "sets_observe_time/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_observe_time.png"),
    # an attempt on the UR5e: per arm geom, how soon an obstacle would touch it, in the observation, c3bf-gym train
    # --observe-contact-time (code 2717fa8), seeds 0 and 1
    ("training_table_sets_ur5e_contact_time.md", "sets_contact_time/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_contact_time.png"),
    # an attempt on the UR5e: the obstacles' clearance 0.5-3 s ahead, to the arm held still and to the goal, in the
    # observation, c3bf-gym train --observe-forecast (code 7615cf2), seeds 0 and 1
    ("training_table_sets_ur5e_forecast.md", "sets_forecast/sac_*", "final_eval.json",
     "training_curves_sets_ur5e_forecast.png"),
    # the default filter's rows under the QP's tool metric, c3bf-gym train --filter-set weight=tool (code a013db5,
    # a = 10 m/s²), seeds 0-4, both arms
    ("training_table_sets_tool_metric_ur5e.md", "sets_tool_metric/sac_*", "final_eval.json",
     "training_curves_sets_tool_metric_ur5e.png"),
    ("training_table_sets_tool_metric_panda.md", "sets_tool_metric/panda_sac_*", "final_eval.json",
     "training_curves_sets_tool_metric_panda.png"),
    # SB3 PPO under the tool metric, c3bf-gym train --algo ppo --filter-set weight=tool (code a013db5), seeds 0-4,
    # both arms, one run at a time beside the SAC sets
    ("training_table_sets_tool_metric_ppo_ur5e.md", "sets_tool_metric_ppo/ppo_*", "final_eval.json",
     "training_curves_sets_tool_metric_ppo_ur5e.png"),
    ("training_table_sets_tool_metric_ppo_panda.md", "sets_tool_metric_ppo/panda_ppo_*", "final_eval.json",
     "training_curves_sets_tool_metric_ppo_panda.png"),
)


def experiment_tables(docs: Path) -> dict[str, str]:
    """``{path under docs/: text}`` of the experiments' tables, from each robot's folder
    (:data:`EXPERIMENT_FOLDERS`) that exists."""
    from c3bf_gym.experiments import COLUMNS, SENSING_COLUMNS, markdown_table

    tables = {}
    for folder in EXPERIMENT_FOLDERS.values():
        if not (docs / folder).is_dir():
            continue
        for name, source, columns in (("experiments", "table.json", COLUMNS), ("sensing", "sensing.json", SENSING_COLUMNS)):
            rows = json.loads((docs / folder / source).read_text())
            tables[f"{folder}/{name}_table.md"] = markdown_table(rows, columns) + "\n"
    return tables


def training_tables(docs: Path, out: Path) -> dict[str, str]:
    """``{path under docs/: text}`` of the training tables, from ``docs/runs``; their figures go to
    ``out``/:data:`TRAINING_FOLDER`."""
    from c3bf_gym.plots import plot_training

    tables = {}
    for name, pattern, evaluation, figure in TRAINING_TABLES:
        runs = sorted((docs / "runs").glob(pattern))
        figure_path = out / TRAINING_FOLDER / figure
        tables[f"{TRAINING_FOLDER}/{name}"] = plot_training(runs, figure_path, evaluation=evaluation) + "\n"
    return tables


def regenerate(docs: Path = DOCS, out: Path | None = None) -> dict[str, str]:
    """Write every table (and the training curves) from ``docs``' results into ``out`` (default:
    ``docs``); returns ``{path under docs/: text}``."""
    out = docs if out is None else out
    out.mkdir(parents=True, exist_ok=True)
    tables = {**experiment_tables(docs), **training_tables(docs, out)}
    for name, text in tables.items():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(text)
    return tables


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--from-run", type=Path, default=None,
                        help=f"first copy {', '.join(RESULT_FILES)} of this c3bf-gym experiments output, and "
                             "its figures that the folder keeps, into "
                             f"docs/{EXPERIMENT_FOLDERS['ur5e']}/ (docs/{EXPERIMENT_FOLDERS['panda']}/ for a run "
                             "with --robot panda)")  # fmt: skip
    parser.add_argument("--out", type=Path, default=DOCS, help="where the tables and the training curves go")
    args = parser.parse_args(argv)
    if args.from_run is not None:
        robot = json.loads((args.from_run / "config.json").read_text()).get("robot", "ur5e")
        target = DOCS / EXPERIMENT_FOLDERS[robot]
        target.mkdir(parents=True, exist_ok=True)
        for name in RESULT_FILES:
            shutil.copyfile(args.from_run / name, target / name)
        for figure in target.glob("*.png"):  # the figures the folder keeps, as the run drew them
            shutil.copyfile(args.from_run / "figures" / figure.name, figure)
    for name in regenerate(DOCS, args.out):
        print(args.out / name)
    return 0


if __name__ == "__main__":
    sys.exit(main())
