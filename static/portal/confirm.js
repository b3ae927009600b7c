/*
 * Forms that ask before they submit: <form data-confirm="question">. Submitting asks the
 * question and sends the form only when the owner agrees. A file of its own, not an onsubmit=
 * attribute: the Content-Security-Policy runs no inline script. Without JavaScript the form
 * submits at once, as it did before.
 */
(function () {
  "use strict";

  document.addEventListener("submit", function (event) {
    var form = event.target;
    if (!(form instanceof HTMLFormElement)) { return; }
    var question = form.getAttribute("data-confirm");
    if (question && !window.confirm(question)) {
      event.preventDefault();
    }
  });
}());
