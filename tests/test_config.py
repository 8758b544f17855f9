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


def test_the_dataset_folder_is_named_by_every_generator_setting():
    """The built-in BTF's folder changes with each generator setting, its defaults
    included (no setting is left out of the name at its default)."""
    from pipeline.btf.stages import synthetic_folder

    cfg = compose_config("experiment=paper_cpu")
    names = {synthetic_folder(cfg).name}
    for override in (
        "dataset.synthetic.material=knit",
        "dataset.synthetic.seed=1",
        "dataset.synthetic.quality=90",
        "dataset.synthetic.size=64",
    ):
        names.add(synthetic_folder(compose_config("experiment=paper_cpu", override)).name)
    assert len(names) == 5
