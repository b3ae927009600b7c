/*
 * The owner's SM4 key, in the browser. The key is generated from the browser's cryptographic
 * random generator (crypto.getRandomValues) as the page loads, shown once to be downloaded
 * as a key file or copied; the owner may type their own instead (the portal refuses one that
 * does not look random). On submit it is encrypted to the portal's SM2 public key (C1C3C2,
 * sm-crypto's cipher mode 1, the paper's key exchange) and only the ciphertext is sent: the
 * key's text field has no name, so the key itself never leaves the page.
 *
 * Markup: a form with data-sm2-public-key, holding [data-sm4-key], input[name=key_ciphertext],
 * [data-generate-key], [data-type-own-key], [data-download-key], [data-copy-key],
 * [data-key-error], [data-key-generated-note], [data-key-copied] and [data-needs-script]
 * controls (disabled until this script has checked that the browser can do the work).
 */
(function () {
  "use strict";

  var KEY_HEX = /^[0-9a-f]{32}$/;

  function toHex(bytes) {
    return Array.prototype.map.call(bytes, function (b) {
      return ("0" + b.toString(16)).slice(-2);
    }).join("");
  }

  function hexToBytes(hex) {
    var bytes = [];
    for (var i = 0; i < hex.length; i += 2) {
      bytes.push(parseInt(hex.substr(i, 2), 16));
    }
    return bytes;
  }

  // The portal refuses a key whose bytes are all printable ASCII or NUL (it looks like text):
  // one random key in 6.5 million does; draw another then (see accounts/services/keys.py).
  function looksLikeText(bytes) {
    return Array.prototype.every.call(bytes, function (b) {
      return b === 0 || (b >= 0x20 && b <= 0x7e);
    });
  }

  function randomKeyHex() {
    var bytes = new Uint8Array(16);
    do {
      window.crypto.getRandomValues(bytes);
    } while (looksLikeText(bytes));
    return toHex(bytes);
  }

  function setUp(form) {
    var publicKey = form.getAttribute("data-sm2-public-key");
    var keyInput = form.querySelector("[data-sm4-key]");
    var cipherField = form.querySelector("input[name='key_ciphertext']");
    var errorBox = form.querySelector("[data-key-error]");
    var generateButton = form.querySelector("[data-generate-key]");
    var typeOwnButton = form.querySelector("[data-type-own-key]");
    var downloadButton = form.querySelector("[data-download-key]");
    var copyButton = form.querySelector("[data-copy-key]");
    var generatedNote = form.querySelector("[data-key-generated-note]");
    var copiedNote = form.querySelector("[data-key-copied]");
    var keptNote = form.querySelector("[data-key-kept]");

    function showError(text) {
      errorBox.textContent = text;
      if (text) {
        keyInput.setAttribute("aria-invalid", "true");
      } else {
        keyInput.removeAttribute("aria-invalid");
      }
    }

    if (!window.sm2 || !window.crypto || !window.crypto.getRandomValues || !publicKey) {
      showError("This browser cannot generate or encrypt the key (no Web Crypto or SM2 " +
                "script), so nothing can be sent. Use a current browser.");
      return;
    }

    function typedKey() {
      return keyInput.value.replace(/\s+/g, "").replace(/^0x/i, "").toLowerCase();
    }

    function keyFilename() {
      var fieldId = form.getAttribute("data-filename-field");
      var field = fieldId ? document.getElementById(fieldId) : null;
      var name = (field && field.value.trim()) || downloadButton.getAttribute("data-filename");
      name = (name || "owner").replace(/\.sm4$/, "").replace(/[^A-Za-z0-9_.-]+/g, "-");
      return name + ".sm4";
    }

    function keyChanged() {
      var valid = KEY_HEX.test(typedKey());
      downloadButton.disabled = !valid;
      copyButton.disabled = !valid;
      copiedNote.hidden = true;
      if (typedKey()) {
        // A new key replaces the one kept (encrypted) from a previous attempt.
        cipherField.value = "";
        if (keptNote) { keptNote.hidden = true; }
      }
      if (valid) { showError(""); }
    }

    function useGeneratedKey() {
      keyInput.readOnly = true;
      keyInput.value = randomKeyHex();
      keyChanged();
      generatedNote.hidden = false;
    }

    generateButton.addEventListener("click", function () {
      useGeneratedKey();
      keyInput.focus();
      keyInput.select();
    });

    typeOwnButton.addEventListener("click", function () {
      keyInput.readOnly = false;
      keyInput.value = "";
      keyChanged();
      generatedNote.hidden = true;
      keyInput.focus();
    });

    downloadButton.addEventListener("click", function () {
      var hex = typedKey();
      if (!KEY_HEX.test(hex)) { return; }
      var blob = new Blob([hex + "\n"], { type: "text/plain" });
      var link = document.createElement("a");
      link.href = URL.createObjectURL(blob);
      link.download = keyFilename();
      document.body.appendChild(link);
      link.click();
      setTimeout(function () {
        URL.revokeObjectURL(link.href);
        link.remove();
      }, 0);
    });

    copyButton.addEventListener("click", function () {
      var hex = typedKey();
      if (!KEY_HEX.test(hex)) { return; }
      function copied() { copiedNote.hidden = false; }
      function selectForCopy() {
        // Without the Clipboard API (a page not served over HTTPS): the owner copies it.
        keyInput.focus();
        keyInput.select();
        if (document.execCommand && document.execCommand("copy")) { copied(); }
      }
      if (navigator.clipboard && window.isSecureContext) {
        navigator.clipboard.writeText(hex).then(copied, selectForCopy);
      } else {
        selectForCopy();
      }
    });

    keyInput.addEventListener("input", keyChanged);

    form.addEventListener("submit", function (event) {
      var hex = typedKey();
      if (!hex && cipherField.value) {
        return; // the key of the previous attempt, still encrypted
      }
      if (!KEY_HEX.test(hex)) {
        event.preventDefault();
        showError("Enter the key as exactly 32 hexadecimal digits (0-9, a-f), or generate one.");
        keyInput.focus();
        return;
      }
      if (/^0+$/.test(hex)) {
        event.preventDefault();
        showError("An all-zero key is not a key: generate one.");
        keyInput.focus();
        return;
      }
      try {
        cipherField.value = window.sm2.doEncrypt(hexToBytes(hex), publicKey, 1);
      } catch (err) {
        event.preventDefault();
        showError("The key could not be encrypted: " + err);
        return;
      }
      showError("");
    });

    // A key from a previous attempt, kept encrypted, stays unless the owner picks another.
    if (!cipherField.value) { useGeneratedKey(); }

    Array.prototype.forEach.call(form.querySelectorAll("[data-needs-script]"), function (el) {
      el.disabled = false;
    });
  }

  Array.prototype.forEach.call(document.querySelectorAll("form[data-sm2-public-key]"), setUp);
})();
