"""A scene rule applied to a run's saved trials (``trials.py``): the rule chosen on val as the
run chooses it (``choose_scene_rule``), or one given, and per split the scene accuracy it
gives and every query it leaves in a wrong scene (query, true, predicted and decided scene,
its refined score in the predicted scene: 'own score'). The test rows read the test labels'
scenes: an audit of a rule, never a way to choose one.

    PYTHONPATH=src python experiments/ms_scene_decision/rules.py trials0.pt
    PYTHONPATH=src python experiments/ms_scene_decision/rules.py trials0.pt 0.4456 3 0.03 0
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from pae.render_compare.scene_decision import SceneRule, choose_scene_rule, evidence, moves


def decided(found: dict, rule: SceneRule) -> tuple[torch.Tensor, torch.Tensor]:
    """The scenes ``rule`` decides for a split's saved trials, and each query's refined score
    in its predicted scene."""
    trials, predicted = found["trials"], found["predicted"]
    own = trials.result.score[torch.arange(len(predicted)), predicted]
    values = evidence(trials, found["prior"], rule.probe_scale, rule.prior_weight)
    target = moves(values, predicted, rule.margin)
    return torch.where(own < rule.check_below, target, predicted), own


def main(path: Path, given: list[str]) -> None:
    saved = torch.load(path, weights_only=False)
    val = saved["val"]
    if given:
        rule = SceneRule(*(float(value) for value in given))
    else:
        rule = choose_scene_rule(val["trials"], val["prior"], val["predicted"], val["truth"])
    print(f"rule: {rule}")
    for split, found in saved.items():
        scenes, own = decided(found, rule)
        truth, predicted = found["truth"], found["predicted"]
        wrong = (scenes != truth).nonzero().flatten().tolist()
        accuracy = 100 * float((scenes == truth).float().mean())
        print(f"{split}: teacher {100 * float((predicted == truth).float().mean()):.1f} %, "
              f"decided {accuracy:.1f} %")  # fmt: skip
        for q in wrong:
            where = f"true {int(truth[q])}, predicted {int(predicted[q])}"
            print(f"  query {q}: {where}, decided {int(scenes[q])}, own score {float(own[q]):.3f}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2:])
