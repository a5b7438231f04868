// Log-in: the server answers with a reason on failure, shown as it is.
const form = document.getElementById("login-form");
const error = document.getElementById("login-error");
form.addEventListener("submit", async (event) => {
  event.preventDefault();
  error.hidden = true;
  let answer;
  try {
    const response = await fetch("/api/login", {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ user: form.user.value.trim(), password: form.password.value }),
    });
    answer = await response.json();
  } catch (e) {
    answer = { ok: false, reason: `the console's server does not answer (${e.message})` };
  }
  if (answer.ok) {
    window.location.assign("/");
  } else {
    error.textContent = answer.reason || "log-in refused";
    error.hidden = false;
    form.password.value = "";
    form.password.focus();
  }
});
