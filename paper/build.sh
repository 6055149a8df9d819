#!/usr/bin/env bash
# Build paper/main.pdf from the figures and tables that `cutfem reproduce` writes into paper/.
# Uses latexmk when present, otherwise pdflatex (run twice for the references).
# Exit status: 0 built; 2 the generated files are missing; 3 no LaTeX installed; 1 LaTeX failed.
set -euo pipefail
cd "$(dirname "$0")"

if [[ ! -f tables/numbers.tex || ! -d figures ]]; then
    echo "paper/build.sh: tables/numbers.tex or figures/ is missing; generate them first with" >&2
    echo "    cutfem reproduce            (quick, a few minutes; --full for the paper's finest levels)" >&2
    exit 2
fi

if command -v latexmk >/dev/null 2>&1 && command -v pdflatex >/dev/null 2>&1; then
    latexmk -pdf -interaction=nonstopmode -halt-on-error -file-line-error main.tex >build.log 2>&1 || {
        echo "paper/build.sh: latexmk failed; the end of paper/build.log:" >&2; tail -n 30 build.log >&2; exit 1; }
elif command -v pdflatex >/dev/null 2>&1; then
    for pass in 1 2; do
        pdflatex -interaction=nonstopmode -halt-on-error -file-line-error main.tex >build.log 2>&1 || {
            echo "paper/build.sh: pdflatex failed (pass $pass); the end of paper/build.log:" >&2; tail -n 30 build.log >&2; exit 1; }
    done
else
    echo "paper/build.sh: neither latexmk nor pdflatex is installed." >&2
    echo "    On Debian/Ubuntu: apt-get install texlive-latex-base texlive-latex-recommended latexmk" >&2
    echo "    (texlive-latex-base gives pdflatex, amsmath and graphicx; -recommended gives geometry and hyperref)." >&2
    exit 3
fi
if grep -q "LaTeX Warning: Reference" main.log 2>/dev/null; then
    echo "paper/build.sh: warning: unresolved references, see paper/main.log" >&2
fi
echo "paper/build.sh: wrote $(pwd)/main.pdf"
