// One confirmation dialog for every command: native <dialog>, so focus and Escape just work.

const dialog = document.getElementById("confirm");

/** Ask before sending; resolves true when the user confirms. */
export function confirmAction(title, text, okLabel = "Send") {
  dialog.querySelector("#confirm-title").textContent = title;
  dialog.querySelector("#confirm-text").textContent = text;
  dialog.querySelector("#confirm-ok").textContent = okLabel;
  dialog.returnValue = "cancel";
  dialog.showModal();
  return new Promise((resolve) => {
    dialog.addEventListener("close", () => resolve(dialog.returnValue === "ok"), { once: true });
  });
}
