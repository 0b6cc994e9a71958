"""Why the skeleton stage holds its output, in words for /diagnostics: one sentence per rule of
skeleton_stage.SkeletonStage.step (the views disagree, one camera holds the markers, the trunk
lies in one image, the maps fade, output resuming, a track back on another body), and what its
link lengths are."""

from __future__ import annotations

from typing import Any


def held_warning(stage: Any, status: str, names: list[str]) -> str | None:
    """The reason the stage recorded at its last step for the status `status` (uncertain or
    lost), naming the settings involved; None when the images did not say so."""
    cfg = stage.config
    if stage.strayed is not None:
        off, bound = stage.strayed
        return (f"{status}: the track came back {off:.2f} m from where the subject was heading (over {bound:.2f} m: "
                f"check_resume_max_m {cfg.check_resume_max_m:g}, more after a gap): another body, the subject is "
                "looked for again")
    if stage.disagreement is not None:
        return stage.disagreement.warning(status, cfg.check_min_agreement, cfg.check_min_support, names)
    if stage.unsupported is not None:
        return (f"{status}: {stage.unsupported:.0%} of this frame set's markers are held by two cameras or more "
                f"(check_min_support {cfg.check_min_support:.0%}), this frame set is not output")
    if stage.outside is not None:
        return (f"{status}: the trunk (hips and shoulders) lies whole in {stage.outside} camera image(s): a body "
                "two cameras do not see is not fixed in space, this frame set is not output")
    if stage.faded is not None:
        return (f"{status}: this frame set's markers weigh {stage.faded:.0%} of the track's recent median "
                f"(check_min_weight_ratio {cfg.check_min_weight_ratio:.0%}): the CNN's maps are fading, "
                "this frame set is not output")
    if stage.resuming is not None:
        return (f"{status}: {stage.resuming} frame set(s) in a row agree with the images after output was held "
                f"(check_resume_frames {cfg.check_resume_frames}), this frame set is not output")
    return None


def lengths_word(stage: Any) -> str:
    """A stage's link lengths in one word: "-" (no skeleton yet), "provisional" (the first fit's,
    output while identification runs and replaced at its end: SkeletonConfig.identify_output)
    or "identified"."""
    return "-" if stage.skeleton is None else "provisional" if stage.provisional else "identified"
