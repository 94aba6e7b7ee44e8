// Inline code breaks only between words: each space-separated token of a command (a path,
// an option, a name) stays whole, so `benchmarks/bench_filter.py` or `--config FILE` never
// splits at a slash or a hyphen. The stylesheet keeps each token on one line (.nm-token);
// without this script it keeps whole code spans in table cells on one line.
(function () {
  var SELECTOR = ".md-typeset td > code, .md-typeset th > code, .md-typeset p > code, " +
                 ".md-typeset li > code, .md-typeset dd > code, .md-typeset td a > code, " +
                 ".md-typeset p a > code, .md-typeset li a > code";
  function keepTokensWhole(root) {
    root.querySelectorAll(SELECTOR).forEach(function (code) {
      if (code.dataset.nmTokens || code.children.length) return;
      code.dataset.nmTokens = "1";
      var text = code.textContent;
      if (!/\S\s+\S/.test(text)) {  // one token: the code span itself stays whole
        code.classList.add("nm-token");
        return;
      }
      code.textContent = "";
      text.split(/(\s+)/).forEach(function (part) {
        if (!part) return;
        if (/^\s+$/.test(part)) {
          code.appendChild(document.createTextNode(part));
        } else {
          var token = document.createElement("span");
          token.className = "nm-token";
          token.textContent = part;
          code.appendChild(token);
        }
      });
      code.classList.add("nm-tokens");
    });
  }
  if (typeof document$ !== "undefined") {
    document$.subscribe(function () { keepTokensWhole(document); });
  } else {
    document.addEventListener("DOMContentLoaded", function () { keepTokensWhole(document); });
  }
})();
