"""Where the pipeline's files live: every path a stage reads or writes, relative to the project root."""

from __future__ import annotations

from pathlib import Path

SUMMARY = Path("metrics/summary.json")

# Every output of a task lives under its name: data/<task>/, models/<task>/, results/<task>/, plots/<task>/ and
# metrics/tasks/<task>/ (the summarize stage reads metrics/tasks); the report writes metrics/report/<task>/.
# What training produces, and what is made from it, has one folder (or file) per training seed, seed<s>, inside
# the phase's; the metrics files of a phase hold every seed's metrics and their aggregate.


def dataset_path(task: str) -> Path:
    """The task's offline training data (expert demonstrations or a behaviour-policy dataset)."""
    return Path(f"data/{task}/dataset.parquet")


def reference_path(task: str) -> Path:
    """What 0 and 100 of the task's normalized score mean (written by its reference stage)."""
    return Path(f"metrics/tasks/{task}/reference.json")


def phase_name(phase: int, control: bool = False) -> str:
    """``phase<k>``, or ``phase<k>-control`` for the equal-compute control of evolution phase k (phase k-1's model
    trained the same steps on expert data only)."""
    return f"phase{phase}-control" if control else f"phase{phase}"


def seed_name(seed: int) -> str:
    """``seed<s>``: the folder of training seed ``s`` inside a phase's models, results and pictures."""
    return f"seed{seed}"


def phase_models_dir(task: str, phase: int, control: bool = False) -> Path:
    """Every training seed's model of a phase (the output of its training stage)."""
    return Path(f"models/{task}/{phase_name(phase, control)}")


def model_dir(task: str, phase: int, seed: int, control: bool = False) -> Path:
    """The model of a phase (or of its control) for one training seed."""
    return phase_models_dir(task, phase, control) / seed_name(seed)


def resume_path(task: str, phase: int, seed: int, control: bool = False) -> Path:
    """Where the training of that model keeps its resume state (ignored by git and DVC; a training stage removes
    its models' states once all of them are saved)."""
    return Path("models") / ".resume" / f"{task}-{phase_name(phase, control)}-{seed_name(seed)}.pt"


def seed_record_dir(task: str, stage: str, phase: int, seed: int, control: bool = False) -> Path:
    """Where a stage that evaluates one training seed after another keeps a seed's finished results until every
    seed's are written (ignored by git and DVC; see :mod:`adaptdiffuser.stages.seed_records`)."""
    return Path("models") / ".resume" / f"{task}-{stage}-{phase_name(phase, control)}-{seed_name(seed)}"


def collect_resume_path(task: str) -> Path:
    """Where the collect stage of a task keeps the state of a long data recipe under way, such as a behaviour
    policy's training (ignored by git and DVC; removed by the recipe once it has no more use)."""
    return Path("models") / ".resume" / f"{task}-collect.pkl"


def value_resume_path(task: str, seed: int) -> Path:
    """Where the training of the task's value function for a training seed keeps its resume state (removed with
    the phase-0 models' states)."""
    return Path("models") / ".resume" / f"{task}-{phase_name(0)}-{seed_name(seed)}-value.pt"


def value_dir(task: str, seed: int) -> Path:
    """The task's learned value function for a training seed, beside its phase-0 model (written by pretrain)."""
    return model_dir(task, 0, seed) / "value"


def collect_dir(task: str) -> Path:
    """The collect stage's summary and the family's own collection outputs, such as behaviour policies."""
    return Path(f"models/{task}/collect")


def results_dir(task: str, phase: int, seed: int, control: bool = False) -> Path:
    return Path(f"results/{task}/{phase_name(phase, control)}/{seed_name(seed)}")


def plots_dir(task: str, phase: int, seed: int, control: bool = False) -> Path:
    return Path(f"plots/{task}/{phase_name(phase, control)}/{seed_name(seed)}")


def phase_metrics_path(task: str, phase: int, control: bool = False) -> Path:
    """Evaluation metrics of a phase or of its control over every training seed (written by its evaluate /
    evaluate-control stage; each seed's own under ``seeds``)."""
    return Path(f"metrics/tasks/{task}/{phase_name(phase, control)}.json")


def discriminator_metrics_path(task: str, phase: int) -> Path:
    """The discriminator report of an evolution phase over every training seed (written by its discriminate
    stage)."""
    return Path(f"metrics/tasks/{task}/phase{phase}-discriminator.json")


def unseen_metrics_path(task: str, phase: int, control: bool = False) -> Path:
    """Metrics of a phase (or of its control) on its family's unseen task over every training seed (written by its
    evaluate-unseen / evaluate-unseen-control stage)."""
    return Path(f"metrics/tasks/{task}/{phase_name(phase, control)}-unseen.json")


def unseen_plots_dir(task: str, phase: int, seed: int, control: bool = False) -> Path:
    return Path(f"plots/{task}/unseen/{phase_name(phase, control)}/{seed_name(seed)}")


def generated_path(task: str, phase: int, seed: int) -> Path:
    """Phase k's generated trajectories for one training seed (from that seed's phase k-1 model)."""
    return Path(f"data/{task}/phase{phase}/generated/{seed_name(seed)}.parquet")


def selected_path(task: str, phase: int, seed: int) -> Path:
    """What the discriminator kept of :func:`generated_path` (trains that seed's phase k model)."""
    return Path(f"data/{task}/phase{phase}/selected/{seed_name(seed)}.parquet")


def discriminator_plot_path(task: str, phase: int, seed: int) -> Path:
    return Path(f"plots/{task}/discriminator/phase{phase}/{seed_name(seed)}.png")


def score_table_path(task: str) -> Path:
    return Path(f"metrics/report/{task}/score_by_phase.csv")


def report_plot_path(task: str) -> Path:
    return Path(f"plots/report/{task}/score_by_phase.png")


def unseen_plot_path(task: str) -> Path:
    return Path(f"plots/report/{task}/unseen_by_phase.png")


#: the metrics (and the results table, ``held_out.parquet``) of the held-out start states (``evaluate.held_out_seed``)
HELD_OUT = "held_out"
