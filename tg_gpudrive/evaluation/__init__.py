"""Scenario-quality evaluation: fidelity, exploitability (CCE-gap), diversity, risk, export, report.

    episodes.py        record_episodes / logged_episodes -> Trajectories (host arrays every metric reads)
    fidelity.py        histograms, Hellinger / KL / W1, realism score (ours, Sim-Agents style)
    exploitability.py  PPO best responses to a frozen profile until their return plateaus; CCE-gap per
                       agent and scenario type, with intervals
    stats.py           Spearman's rho of a knob with a figure and its bootstrap interval
    diversity.py       mean pairwise displacement of a scene's episodes
    risk.py            collisions, min TTC, min gap, hard braking, ranking of critical scenarios
    export.py          scenes and generated episodes to GPUDrive processed JSON
    report.py          `tg-gpudrive report`: collects the runs' episodes and gaps (cached), report_main
    report_stats.py    the report's figures of merit: per-policy measures, knob directions, worst scenes
    report_figures.py  its plots: the grid of trajectories, multipliers, gaps and their curves, worst scenes
    report_markdown.py report.md (the findings) and per_agent.csv / per_scene.csv beside it
    generate.py        `tg-gpudrive generate`: fine-tune under beta and alpha, export the critical scenarios
"""
