"""MkDocs hook: files that live outside docs/ but belong on the site.

The studies' committed figures (`experiments/results/**.png`) are published at
`experiments/results/...`, beside the Experiments page (`experiments/index.md`), so that
experiments/README.md, included into that page, shows its figures through its own relative links
(`results/NAME/figure.png`).
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[2]
PUBLISHED = (("experiments/results", "*.png"),)


def on_files(files: Files, config) -> Files:
    for folder, pattern in PUBLISHED:
        for path in sorted((ROOT / folder).rglob(pattern)):
            relative = path.relative_to(ROOT).as_posix()
            if files.get_file_from_path(relative) is None:
                files.append(
                    File(
                        relative,
                        src_dir=str(ROOT),
                        dest_dir=config["site_dir"],
                        use_directory_urls=config["use_directory_urls"],
                    )
                )
    return files
