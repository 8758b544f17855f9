"""Config composition: a group chosen on the command line wins over an experiment's."""

import pytest
from helpers import compose_config


@pytest.mark.parametrize("experiment", ["default", "paper_cpu", "paper"])
def test_train_paper_on_the_command_line_trains_with_the_papers_sgd(experiment):
    cfg = compose_config(f"experiment={experiment}", "train=paper")
    assert (cfg.train.optimizer, cfg.train.batch_size, cfg.train.epochs) == ("sgd", 5, 20)


def test_the_main_job_keeps_its_cpu_recipe_when_no_train_group_is_chosen():
    cfg = compose_config()
    assert (cfg.train.optimizer, cfg.train.batch_size, cfg.train.threads) == ("adam", 32, 1)


def test_settings_added_later_keep_the_folders_and_keys_made_before_them():
    """dataset.synthetic.material and dataset.linearize came after paper-scale runs were
    cached; at their defaults the dataset folder and the evaluate key are as before."""
    from pipeline.btf.stages import synthetic_folder, without_added_defaults
    from pipeline.core.stage import plain_settings

    cfg = compose_config("experiment=paper_cpu")
    assert (cfg.dataset.synthetic.material, cfg.dataset.linearize) == ("plain_weave", None)
    # The name the code of f664425 (before both settings) gave this dataset.
    assert synthetic_folder(cfg).name == "synthetic_btf-ubo2003-jpg-ec502f9c82"
    assert without_added_defaults(plain_settings(cfg.dataset)) == {
        "name": "synthetic", "format": "ubo2003", "root": None, "views": None,
        "synthetic": {"size": 128, "seed": 0, "ext": "jpg", "quality": 95}}
    knit = compose_config("experiment=paper_cpu", "dataset.synthetic.material=knit")
    assert synthetic_folder(knit) != synthetic_folder(cfg)
