"""The report's section on the prior: what it was, how its strength was chosen, what the data taught.

Reads ``calibration.json`` ``prior`` (:func:`torchcal.stages.prior_options.prior_metadata`).
"""

from __future__ import annotations

from torchcal.report.document import Paragraph, Preformatted, Section, Table


def prior_sections(metadata: dict) -> list[Section]:
    """One section "Prior and posterior" for a MAP fit; none for a fit without a prior."""
    prior = metadata.get("prior")
    if not prior:
        return []
    blocks: list = [Paragraph(
        f"The fit combines the measurements with a prior: {prior['source']}. Every robot parameter is estimated; "
        "where the data say nothing the parameter stays at the prior mean with the prior's sigma (posterior/prior sigma "
        "near 1), where they say much the posterior sigma is a small fraction of the prior's. 'moved' is how far the "
        "data moved the parameter from the prior mean, in prior sigmas; a parameter further than its tolerance "
        f"({prior.get('tolerance_band_sigmas', 3):g} unscaled sigmas) is named in the notes. {prior['summary']}.")]
    selection = prior.get("selection")
    if selection:
        blocks.append(Paragraph(f"The prior's strength was chosen by {selection['protocol']}: {selection['chosen']} "
                                f"({selection['reason']})."))
        blocks.append(Preformatted(selection["table"]))
    rows = [[r["name"], r["unit"], f"{r['prior']:.5f}", f"{r['prior_sigma']:.3g}", f"{r['posterior']:.5f}",
             f"{r['posterior_sigma']:.3g}", f"{r['moved_sigmas']:+.2f}", f"{r['sigma_ratio']:.3f}",
             "beyond tolerance" if r["beyond_tolerance"] else ""] for r in prior["parameters"]]
    blocks.append(Table("prior", ["parameter", "unit", "prior", "prior sigma", "posterior", "posterior sigma",
                                  "moved (prior sigmas)", "posterior/prior sigma", "note"], rows))
    return [Section("Prior and posterior", blocks)]
